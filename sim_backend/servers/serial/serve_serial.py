"""Serve the simulated drive over a serial ASCII dialect on a pseudo-terminal.

``servobench serve-sim --transport serial [--dialect odrive]`` opens a pty
pair, announces ``serial:///dev/pts/N?baud=115200&dialect=odrive`` and
answers the dialect (:mod:`servobench.drivers.serial.dialect`) on the master end, as an ODrive
answers its ASCII protocol on ``/dev/ttyACM0``. The client opens the slave
path with pyserial like any serial port.

Lock-step semantics: the torque command (``c``) latches; the feedback query
(``f``) clocks the device one cycle -- the reply is the sample at ``t_k``, then
the latched command acts over ``[t_k, t_{k+1})``. Property reads (``r``) never
clock. A ``clock="real"`` device (``serve-sim``'s default) samples the axis as
it stands in wall-clock time when the query's last byte has arrived on the
emulated line; the dialect carries no time stamp. Units: the plant's command unit is served as Nm, its position unit as
turn and its velocity unit as turn/s, one to one.

A dialect that names a ``firmware_model`` is answered as that firmware
does: ``odrive-0.5`` is :class:`~servobench.sim_backend.servers.serial.odrive_firmware.OdriveFirmware`
at the release the ``firmware`` option names (``0.5.1`` ... ``0.5.6``,
default 0.5.6): its rejection texts, its property tree, a watchdog fed only
by ``c``/``u`` and closed-loop entry and checked in every axis state.
Other dialects get the generic server: every valid request line feeds the
device watchdog, and requests are matched against the dialect's templates.
When the host falls silent the device faults by itself
(``servobench.sim_backend.servers.serve`` runs a
:class:`~servobench.sim_backend.device.WatchdogThread`), and error reads then report the
dialect's watchdog flag (``WATCHDOG_TIMER_EXPIRED``, 0x800, for ODrive).

Sessions: the server does not hold the pty's client end open, so it sees
when no client has it open; a client opening it begins a host session
(:meth:`~servobench.sim_backend.device.SimulatedDevice.begin_session`): the
drive clock restarts and a half-received line is dropped. Request lines end
at any of the dialect's ``line_ends`` (ODrive: ``\r``, ``\n`` and ``!``).

Byte time
---------
A pty moves bytes in microseconds and has no baud rate, so a rate measured
over it would flatter the protocol. The server keeps a UART clock per
direction (8N1: 10 bits per byte, ``t_char = 10 / baud``, 86.8 us at 115200):
a request line counts as received when its last byte would have arrived
(``max(read time, rx line free) + (i + 1) * t_char``), and a reply of ``n``
bytes is written only when its last byte would have left
(``max(now, tx line free) + n * t_char``). A lock-step exchange therefore
costs at least ``(request + reply bytes) * t_char``, as on a real 115200 baud
link. Waits sleep to within :data:`SPIN_S` of the deadline, then spin.

Fault injection (``--fault``, the grammar of :mod:`servobench.sim_backend.faults.spec`;
``N`` counts feedback queries from 1): ``fault@N[:C]`` faults the drive
(dialect flag ``other``) before answering, ``freeze@N`` stops position and
velocity, and the wire faults of :mod:`servobench.sim_backend.faults.serial` --
``garble@N``, ``truncate@N``, ``interleave@N``, ``drop@N`` (``silence@N``),
``dup@N``, ``delay@N:MS`` -- mangle the N-th feedback reply (the drive is
clocked in every case).
"""

from __future__ import annotations

import contextlib
import errno
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Mapping
from urllib.parse import quote

from servobench.clock import sleep_until
from servobench.drivers.serial.ascii_line import decode_request, encode_line
from servobench.drivers.serial.dialect import DEFAULT_DIALECT, Dialect, load_dialect, parse_version
from servobench.errors import DriveConfigError, DriveFaultError
from servobench.sim_backend.device import WATCHDOG_FAULT, PowerState, SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.serial import SerialFaultHook
from servobench.sim_backend.faults.spec import FaultPlan, parse_plan
from servobench.sim_backend.servers.serial.odrive_firmware import (
    DEFAULT_VERSION,
    FEEDBACK,
    OdriveFirmware,
)

#: Baud rate announced and emulated when the options name none [bit/s].
DEFAULT_BAUD = 115200
#: Bits per byte on the wire, 8N1.
BITS_PER_BYTE = 10
#: How often the serve loop looks at the stop event [s].
STOP_POLL_S = 0.05
#: Last part of a byte-time wait that is spun rather than slept [s].
SPIN_S = 2e-4
#: Longest request line; longer ones are dropped up to the next line end (as the ODrive does).
MAX_LINE_BYTES = 255
#: DC bus voltage the simulated drive reports [V].
SIM_VBUS_V = 24.0
#: How often a port nobody has open is looked at for a client opening it [s].
HANGUP_POLL_S = 0.01


def parse_faults(spec: str) -> FaultPlan:
    """``"garble@50;silence@80"`` as a :class:`~servobench.sim_backend.faults.spec.FaultPlan`."""
    return parse_plan(spec, "serial")


class AsciiDriveServer:
    """The drive side of a dialect: request line in, reply bytes out.

    Parameters
    ----------
    device : SimulatedDevice
        The simulated drive.
    dialect : Dialect
        What to understand and how to answer.
    faults : FaultPlan or FaultInjector, optional
        Faults to inject, by feedback-query number (see module doc).
    firmware : tuple of int, optional
        Release of the dialect's ``firmware_model`` to emulate (default: the latest modelled).
    """

    def __init__(
        self,
        device: SimulatedDevice,
        dialect: Dialect,
        faults: FaultPlan | FaultInjector | None = None,
        firmware: tuple[int, ...] | None = None,
    ) -> None:
        self.device = device
        self.dialect = dialect
        self.firmware: OdriveFirmware | None = None
        if dialect.firmware_model == "odrive-0.5":
            try:
                # a real-time axis runs its own loop, as a stock ODrive: no lock-step extension
                lockstep = "set_cycle" in dialect.extensions and not device.realtime
                self.firmware = OdriveFirmware(device, firmware or DEFAULT_VERSION, lockstep)
            except ValueError as err:
                raise DriveConfigError(str(err)) from None
        elif firmware is not None:
            raise DriveConfigError(f"dialect {dialect.name!r} names no firmware model to version")
        if not isinstance(faults, FaultInjector):
            faults = FaultInjector(device, faults or FaultPlan("serial"))
        self.injector = faults
        self.hook = SerialFaultHook()
        self._watchdog_timeout_s = device.watchdog_s or 0.0
        self._watchdog_enabled = device.watchdog_s is not None
        self._handlers: dict[str, Callable[..., list[str]]] = {
            "torque": self._torque,
            "enable": self._enable,
            "disable": self._disable,
            "state": self._state,
            "error": self._error,
            "clear_errors": self._clear_errors,
            "watchdog_timeout": self._watchdog_timeout,
            "watchdog_enable": self._watchdog_enable,
            "watchdog_feed": lambda: [],
            "watchdog_readback": self._watchdog_readback,
            "position": lambda: [self.dialect.reply("position", x=self.injector.sample().position)],
            "velocity": lambda: [self.dialect.reply("velocity", v=self.injector.sample().velocity)],
            "vbus": lambda: [self.dialect.reply("vbus", value=SIM_VBUS_V)],
            "info": self._info,
            "quick_stop": self._quick_stop,
            "set_cycle": self._set_cycle,
            "cycle_readback": lambda: [self.dialect.reply("cycle", period_s=self.device.cycle_s)],
        }

    def begin_session(self) -> None:
        """A client opened the port: the drive starts the session clean."""
        self.device.begin_session()

    def handle(self, raw: bytes) -> bytes:
        """Reply bytes (possibly several lines, possibly none) to one request line."""
        req = decode_request(raw)
        if not req.valid:
            return b""  # bad checksum or not ASCII: ignored, as the ODrive does
        if self.firmware is not None:
            out = self.firmware.handle(req.body)
            if out is FEEDBACK:
                return self._feedback_bytes(req.checksummed)
            return self._encode(out, req.checksummed)  # type: ignore[arg-type]
        if not req.body:
            return b""
        d = self.dialect
        parsed = d.match_request(req.body)
        if parsed is None:
            return self._encode([d.rejections["unknown"]], req.checksummed)
        fields = dict(parsed.fields)
        axis = fields.pop("axis", d.axis)
        if axis != d.axis:
            return self._encode([f"{d.rejections['axis']} {axis}"], req.checksummed)
        self.device.feed()
        if parsed.name == "feedback":
            return self._feedback_bytes(req.checksummed)
        return self._encode(self._handlers[parsed.name](**fields), req.checksummed)

    def _encode(self, bodies: list[str], checksum: bool) -> bytes:
        term = self.dialect.reply_terminator
        return b"".join(encode_line(b, term, checksum) for b in bodies)

    # ------------------------------------------------------------ commands
    def _torque(self, u: float) -> list[str]:
        self.device.set_command(u)
        return []

    @property
    def feedback_count(self) -> int:
        """Feedback queries answered (or not) so far."""
        return self.injector.cycle

    def _feedback_bytes(self, checksum: bool) -> bytes:
        wire = self.injector.next_cycle()
        s = self.injector.step()
        raw = self._encode([self.dialect.reply("feedback", x=s.position, v=s.velocity)], checksum)
        reply = self.hook.reply(wire, raw, self.dialect.reply_terminator)
        if reply.delay_s > 0:
            time.sleep(reply.delay_s)  # the drive is late; requests queue up meanwhile
        return reply.data

    def _enable(self) -> list[str]:
        with contextlib.suppress(DriveFaultError):  # refused: stays idle, the error stays set
            self.device.enable()
        return []

    def _disable(self) -> list[str]:
        self.device.disable()
        return []

    def _quick_stop(self) -> list[str]:
        self.device.quick_stop()
        return []

    def _state(self) -> list[str]:
        enabled = self.device.state is PowerState.ENABLED
        code = self.dialect.states["enabled" if enabled else "disabled"]
        return [self.dialect.reply("state", state=code)]

    def _error(self) -> list[str]:
        code = self.device.fault_code
        if code:
            d = self.dialect
            code = d.watchdog_error if code == WATCHDOG_FAULT else d.other_error
        return [self.dialect.reply("error", code=code)]

    def _clear_errors(self) -> list[str]:
        self.device.reset_fault()
        return []

    def _watchdog_timeout(self, timeout_s: float) -> list[str]:
        if timeout_s < 0:
            return [self.dialect.rejections["format"]]
        self._watchdog_timeout_s = timeout_s
        if self._watchdog_enabled:
            self.device.set_watchdog(timeout_s or None)
        return []

    def _watchdog_enable(self) -> list[str]:
        self._watchdog_enabled = True
        self.device.set_watchdog(self._watchdog_timeout_s or None)
        return []

    def _watchdog_readback(self) -> list[str]:
        return [self.dialect.reply("watchdog_timeout", timeout_s=self._watchdog_timeout_s)]

    def _set_cycle(self, period_s: float) -> list[str]:
        try:
            self.device.set_cycle(period_s)
        except ValueError:
            return [self.dialect.rejections["format"]]
        return []

    def _info(self) -> list[str]:
        text = {
            "hardware": "servobench simulated drive",
            "firmware": f"servobench-sim ({self.dialect.name} dialect)",
            "serial_number": "SIM000000001",
        }
        return [t.format("", text=text[k]) for k, t in self.dialect.info.items()]


# ------------------------------------------------------------------ the wire
class UartClock:
    """Byte-time bookkeeping of a full-duplex UART (see module doc).

    Parameters
    ----------
    baud : int
        Bit rate [bit/s]; 10 bits per byte.
    """

    def __init__(self, baud: int) -> None:
        if not baud > 0:
            raise DriveConfigError(f"baud must be > 0, got {baud}")
        self.char_s = BITS_PER_BYTE / baud
        self._rx_free = 0.0
        self._tx_free = 0.0

    def receive(self, n: int, now: float) -> float:
        """``n`` bytes read at ``now``: return when the first of them started arriving."""
        start = max(now, self._rx_free)
        self._rx_free = start + n * self.char_s
        return start

    def transmit(self, n: int, now: float) -> float:
        """``n`` bytes to send from ``now``: return when the last of them has left."""
        self._tx_free = max(now, self._tx_free) + n * self.char_s
        return self._tx_free


class PtyPort:
    """A pseudo-terminal pair in raw mode: the server uses :attr:`master`, clients open :attr:`path`.

    The client end is not held open here: while no client has it open the
    master sees a hang-up (:meth:`hung_up`), so the server knows when a
    client opens the port (a new host session). A client may close and
    reopen it at any time (a killed host, then a fresh one).
    """

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(slave)
        os.close(slave)
        self._hangup = select.poll()
        self._hangup.register(self.master, 0)  # POLLHUP is always reported

    def hung_up(self) -> bool:
        """True while no client has the port open."""
        return bool(self._hangup.poll(0))

    def close(self) -> None:
        with contextlib.suppress(OSError):
            os.close(self.master)

    def __enter__(self) -> PtyPort:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _lines(data: bytes, ends: bytes) -> list[tuple[int, bytes | None]]:
    """``(index of the line end, text before it)`` for each line end in ``data``; the rest last.

    The rest (no line end after it) comes as ``(-1, bytes)``.
    """
    out: list[tuple[int, bytes | None]] = []
    start = 0
    for i, byte in enumerate(data):
        if byte in ends:
            out.append((i, data[start:i]))
            start = i + 1
    out.append((-1, data[start:]))
    return out


def pump(
    fd: int,
    server: AsciiDriveServer,
    clock: UartClock,
    stop: threading.Event,
    port: PtyPort | None = None,
) -> None:
    """Read request lines from ``fd``, answer them at UART pace, until ``stop`` is set.

    With ``port``, a client opening it begins a host session (:meth:`AsciiDriveServer.begin_session`).
    """
    pending = bytearray()
    dropping = False  # inside an over-long line: ignore up to its end
    ends = server.dialect.line_ends
    hung = port is not None  # no client has the port open (yet)
    while not stop.is_set():
        if hung and port is not None and not port.hung_up():
            hung = False  # a client opened the port: a new host session
            server.begin_session()
        ready, _, _ = select.select([fd], [], [], STOP_POLL_S)
        if not ready:
            continue
        try:
            data = os.read(fd, 4096)
        except BlockingIOError:
            continue
        except OSError as err:
            if err.errno != errno.EIO:  # EIO: no client has the port open, nothing left to read
                raise
            if not hung:
                hung, dropping = True, False
                pending.clear()
            stop.wait(HANGUP_POLL_S)
            continue
        if hung and port is not None:  # lines of a client that came and went between two looks
            hung = False
            server.begin_session()
        start = clock.receive(len(data), time.monotonic())
        for k, text in _lines(data, ends):
            if k < 0:
                pending += text
                if len(pending) > MAX_LINE_BYTES:
                    pending.clear()
                    dropping = True
                break
            line = bytes(pending) + text
            pending.clear()
            if dropping or len(line) > MAX_LINE_BYTES:
                dropping = False
                continue
            sleep_until(start + (k + 1) * clock.char_s, SPIN_S)
            reply = server.handle(line)
            if reply:
                sleep_until(clock.transmit(len(reply), time.monotonic()), SPIN_S)
                with contextlib.suppress(BlockingIOError):  # nobody reads: bytes are lost
                    os.write(fd, reply)


def serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None = None,
) -> None:
    """Serve ``device`` on a pty until ``stop`` is set (see :mod:`servobench.sim_backend.servers.serve`).

    Options used: ``dialect`` (name or TOML file, default ``odrive``), ``baud``
    (emulated bit rate, default 115200), ``firmware`` (release of the
    dialect's firmware model, e.g. ``0.5.1``) and ``fault`` (``;``-separated
    ``KIND@N`` specs).
    """
    dialect_ref = options.get("dialect") or DEFAULT_DIALECT
    dialect = load_dialect(dialect_ref)
    baud = int(options.get("baud") or DEFAULT_BAUD)
    clock = UartClock(baud)
    firmware = parse_version(options["firmware"]) if options.get("firmware") else None
    if injector is None:
        injector = FaultInjector(device, parse_faults(options.get("fault") or ""))
    server = AsciiDriveServer(device, dialect, injector, firmware)
    with PtyPort() as port:
        announce(f"serial://{port.path}?baud={baud}&dialect={quote(dialect_ref, safe='/')}")
        pump(port.master, server, clock, stop, port)
