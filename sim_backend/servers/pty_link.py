"""A virtual serial cable between two pseudo-terminals, optionally at a real baud rate.

:class:`PtyLink` opens two pty pairs and copies bytes between their master
ends in a thread: a program that opens :attr:`PtyLink.a_path` talks to one
that opens :attr:`PtyLink.b_path`, like two serial ports joined by a null-modem
cable. A pty has no baud rate (bytes pass in microseconds), so the link
emulates the line: a burst written by one side (a frame) occupies the wire
for one character time per byte, and the receiver gets it whole when it
would see the frame end, ``frame_gap_s`` of silence after the last byte (the
Modbus RTU t3.5 rule; 0 for protocols that end frames in-band)::

    sender writes n bytes at t0  ->  on the wire  [start, start + n * t_char)
                                     start = max(t0, previous frame end + frame_gap_s)
                                     delivered at  start + n * t_char + frame_gap_s
    t_char = bits_per_char / baud    (10 bits for 8N1: 86.8 us at 115200 baud)

Bytes that arrive while the previous ones are still "on the wire" extend the
same frame. Without ``baud`` and gap, bytes pass through at once.

The B end's slave stays open inside the link, so the server's side never
sees a hang-up. The A end's slave is left to the client: while no program
has it open, the link sees a hang-up on A (and drops every frame then in
flight: answers to a host that is gone); when one opens it, the link calls ``on_open`` -- a new host session (the
served drive starts it clean, :meth:`~servobench.sim_backend.device.SimulatedDevice.begin_session`).
A client may close and reopen its end (a killed host, a fresh client) at any time.

Fault injection: :meth:`PtyLink.tamper_next` rewrites the next frame the B
end sends (the served drive's next answer) on its way to A, e.g. to corrupt
a Modbus RTU CRC.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import select
import sys
import threading
import time
import tty
from collections import deque
from collections.abc import Callable

#: Bits on the wire per byte for 8N1: start + 8 data + stop.
BITS_8N1 = 10
_READ_SIZE = 4096
_PR_SET_TIMERSLACK = 29
#: How often a hung-up A end is looked at for a client opening it [s].
HANGUP_POLL_S = 0.01


def _tighten_timer_slack() -> None:
    """Let this thread's timed waits end within ~1 us instead of Linux's default 50 us.

    Best effort (Linux ``prctl(PR_SET_TIMERSLACK)``); elsewhere delivery is just
    up to 50 us later.
    """
    if not sys.platform.startswith("linux"):
        return
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_TIMERSLACK, 1000, 0, 0, 0)


def _write(fd: int, data: bytes) -> None:
    """Write what the far end's buffer takes; the rest is lost, as on a UART nobody reads."""
    with contextlib.suppress(BlockingIOError, InterruptedError):
        os.write(fd, data)


Tamper = Callable[[bytes], bytes]


class _Direction:
    """Frames in flight one way, each with the time the receiver sees it complete."""

    def __init__(self, src: int, dst: int) -> None:
        self.src, self.dst = src, dst
        # ([deliver at [s]], bytes, rewrite of the whole frame or None)
        self.frames: deque[tuple[list[float], bytearray, Tamper | None]] = deque()
        self.last_due_s = -math.inf  # when the last byte accepted so far is off the wire
        self.tamper: Tamper | None = None  # applied to the next new frame

    def accept(self, data: bytes, now: float, t_char_s: float, gap_s: float) -> None:
        if self.frames and now < self.last_due_s:  # the sender is still transmitting: same frame
            start = self.last_due_s
        else:  # a new frame: it starts after the silence that ended the previous one
            start = max(now, self.last_due_s + gap_s)
            tamper, self.tamper = self.tamper, None
            self.frames.append(([0.0], bytearray(), tamper))
        self.last_due_s = start + len(data) * t_char_s
        deliver_at, buf, _ = self.frames[-1]
        buf += data
        deliver_at[0] = self.last_due_s + gap_s

    def deliver(self, now: float) -> None:
        while self.frames and self.frames[0][0][0] <= now:
            _, buf, tamper = self.frames.popleft()
            _write(self.dst, bytes(buf) if tamper is None else tamper(bytes(buf)))

    def next_wake(self) -> float | None:
        return self.frames[0][0][0] if self.frames else None

    def drop(self) -> None:
        """Forget every frame in flight (the receiver hung up)."""
        self.frames.clear()
        self.last_due_s = -math.inf


class PtyLink:
    """Two pseudo-terminals joined by a (baud-rate emulating) byte pump.

    Parameters
    ----------
    baud : int or None
        Line rate to emulate [bit/s]; ``None`` passes bytes through at once.
    bits_per_char : int
        Bits per byte on the wire (10 for 8N1).
    """

    def __init__(
        self,
        baud: int | None = None,
        bits_per_char: int = BITS_8N1,
        frame_gap_s: float = 0.0,
        on_open: Callable[[], None] | None = None,
    ) -> None:
        if baud is not None and baud <= 0:
            raise ValueError("baud must be > 0")
        if frame_gap_s < 0:
            raise ValueError("frame_gap_s must be >= 0")
        self.baud = baud
        self.t_char_s = 0.0 if baud is None else bits_per_char / baud
        self.frame_gap_s = frame_gap_s
        self._fds: list[int] = []
        self.a_path = self.b_path = ""
        self._thread: threading.Thread | None = None
        self._wake_r = self._wake_w = -1
        self._stopping = False
        self._dirs: list[_Direction] = []
        self.on_open = on_open
        #: Times a client opened the A end.
        self.opens = 0

    def _pair(self, keep_slave: bool) -> tuple[int, str]:
        master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(master, False)
        path = os.ttyname(slave)
        if keep_slave:
            self._fds += [master, slave]
        else:
            os.close(slave)
            self._fds.append(master)
        return master, path

    def start(self) -> PtyLink:
        """Create the pty pairs and start pumping. Returns ``self``."""
        master_a, self.a_path = self._pair(keep_slave=False)
        master_b, self.b_path = self._pair(keep_slave=True)
        self._wake_r, self._wake_w = os.pipe()
        self._fds += [self._wake_r, self._wake_w]
        dirs = [_Direction(master_a, master_b), _Direction(master_b, master_a)]
        self._dirs = dirs
        self._thread = threading.Thread(
            target=self._run, args=(dirs,), name="pty-link", daemon=True
        )
        self._thread.start()
        return self

    def _run(self, dirs: list[_Direction]) -> None:
        _tighten_timer_slack()
        master_a = dirs[0].src
        looks = select.poll()
        looks.register(master_a, select.POLLIN)  # POLLHUP is reported whatever is asked
        hung = True
        while not self._stopping:
            events = looks.poll(0)
            closed = any(ev & select.POLLHUP for _, ev in events)
            waiting = any(ev & select.POLLIN for _, ev in events)
            if closed and not hung:  # the client went: answers in flight have nobody to go to
                hung = True
                for d in dirs:
                    d.drop()
            if hung and (not closed or waiting):  # a client opened A (and maybe left already)
                hung = closed
                self._opened()
            watch = [d.src for d in dirs if d.src != master_a or not closed or waiting]
            now = time.monotonic()
            wakes = [w for d in dirs if (w := d.next_wake()) is not None]
            if closed and not waiting:
                wakes.append(now + HANGUP_POLL_S)
            timeout = max(0.0, min(wakes) - now) if wakes else None
            readable, _, _ = select.select([*watch, self._wake_r], [], [], timeout)
            now = time.monotonic()
            for d in dirs:
                if d.src in readable:
                    try:
                        data = os.read(d.src, _READ_SIZE)
                    except (BlockingIOError, InterruptedError):
                        data = b""
                    except OSError:  # EIO: A hung up (seen next round), or the link closed
                        if self._stopping:
                            return
                        data = b""
                    if data:
                        d.accept(data, now, self.t_char_s, self.frame_gap_s)
                d.deliver(now)

    def _opened(self) -> None:
        self.opens += 1
        if self.on_open is not None:
            self.on_open()

    def tamper_next(self, rewrite: Tamper) -> None:
        """Rewrite the next frame sent from B to A with ``rewrite(frame) -> frame`` (once)."""
        if not self._dirs:
            raise RuntimeError("the link is not started")
        self._dirs[1].tamper = rewrite

    def close(self) -> None:
        """Stop the pump and close every descriptor. Safe to call twice."""
        self._stopping = True
        if self._wake_w >= 0:
            with contextlib.suppress(OSError):
                os.write(self._wake_w, b"x")
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)
        self._fds = []
        self._wake_r = self._wake_w = -1

    def __enter__(self) -> PtyLink:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
