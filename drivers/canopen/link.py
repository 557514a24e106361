"""The CAN side of ``canopen://``: EDS loading, the tapped network, the host heartbeat, counters.

Kept apart from :mod:`servobench.drivers.canopen.drive` (the CiA 402 drive logic) so each
stays small. Sent frames pass through :class:`TappedNetwork`, which can feed
a :class:`TrafficRecorder` (python-can log formats) together with the
received frames, under one lock, with the send time and direction.
"""

from __future__ import annotations

import io
import os
import socket
import threading
import time
from importlib import resources

import can
import canopen
from can.interfaces.socketcand.socketcand import (
    SocketCanDaemonBus,
    convert_can_message_to_ascii_message,
)

from servobench.errors import DriveConnectionError, DriveTimeoutError

#: Deadline for reaching a socketcand server over TCP [s] (python-can itself retries for 10 s).
CONNECT_TIMEOUT_S = 2.0
#: Deadline for each answer of the socketcand handshake (``< hi >``, ``< ok >``) [s]: python-can
#: waits for them forever, so a port that is no socketcand server would hang it.
HANDSHAKE_TIMEOUT_S = 1.0


#: The generic CiA 402 EDS servobench ships (types of the standard objects).
GENERIC_EDS = "cia402"


def shipped_eds() -> list[str]:
    """Names of the EDS files servobench ships (``cia402``, ``zeroerr-edriver``, ...)."""
    folder = resources.files("servobench.drivers").joinpath("data")
    return sorted(p.name[:-4] for p in folder.iterdir() if p.name.endswith(".eds"))


def load_eds(node_id: int, path: str | None = None) -> canopen.ObjectDictionary:
    """The object dictionary of the EDS file ``path``, or of a shipped EDS named by its
    stem (``eds=zeroerr-edriver``); default the shipped generic CiA 402 EDS."""
    name = path or GENERIC_EDS
    if path and (os.path.exists(path) or name not in shipped_eds()):
        return canopen.import_od(path, node_id)
    data = resources.files("servobench.drivers").joinpath(f"data/{name}.eds")
    stream = io.StringIO(data.read_text("ascii"))
    stream.name = f"{name}.eds"
    return canopen.import_od(stream, node_id)


def _expect(sock: socket.socket, want: str, where: str, deadline: float) -> None:
    """Read one ``< ... >`` answer before ``deadline`` and check that it is ``want``."""
    text = b""
    while b">" not in text:
        left = deadline - time.monotonic()
        if left <= 0:
            raise DriveTimeoutError(
                f"{where} is no socketcand server: no '{want}' within {HANDSHAKE_TIMEOUT_S} s"
                + (f" (got {text[:40]!r})" if text else "")
            )
        sock.settimeout(left)
        try:
            chunk = sock.recv(256)
        except TimeoutError:
            continue
        if not chunk:
            raise DriveConnectionError(f"{where} closed the connection before '{want}'")
        text += chunk
    answer = text[text.find(b"<") : text.find(b">") + 1].decode("ascii", "replace")
    if " ".join(answer.split()) != want:
        raise DriveConnectionError(f"{where} answered {answer!r} where socketcand says '{want}'")


def probe_socketcand(host: str, port: int, channel: str) -> None:
    """Check that ``host:port`` is a socketcand server serving ``channel``, under deadlines.

    Connects (:data:`CONNECT_TIMEOUT_S`), expects the greeting ``< hi >``, opens
    the bus and expects ``< ok >`` (:data:`HANDSHAKE_TIMEOUT_S` each), then
    closes. python-can's own client waits for these answers without a
    time-out; this makes a wrong port a one-line error instead of a hang.
    """
    where = f"{host}:{port}"
    try:
        sock = socket.create_connection((host, port), timeout=CONNECT_TIMEOUT_S)
    except OSError as err:
        raise DriveConnectionError(
            f"cannot reach the socketcand server {where}: {err.strerror or err}"
        ) from err
    try:
        _expect(sock, "< hi >", where, time.monotonic() + HANDSHAKE_TIMEOUT_S)
        sock.sendall(f"< open {channel} >".encode("ascii"))
        _expect(sock, "< ok >", f"{where} (bus {channel})", time.monotonic() + HANDSHAKE_TIMEOUT_S)
    except OSError as err:
        if isinstance(err, (DriveConnectionError, DriveTimeoutError)):
            raise
        raise DriveConnectionError(f"socketcand handshake with {where} failed: {err}") from err
    finally:
        sock.close()


class CounterUnwrap:
    """Undo the wrap-around of a ``bits``-wide counter (0x6064, 0x1013)."""

    def __init__(self, bits: int) -> None:
        self.modulus = 1 << bits
        self.last: int | None = None
        self.total = 0

    def __call__(self, raw: int) -> int:
        if self.last is None:
            self.total = raw
        else:
            delta = (raw - self.last) % self.modulus
            self.total += delta - self.modulus if delta >= self.modulus // 2 else delta
        self.last = raw
        return self.total


class TappedNetwork(canopen.Network):
    """canopen's network, with a tap on sent frames for :meth:`Drive.record_traffic`."""

    #: Receive-thread wake-up period [s]; closing waits up to this long.
    NOTIFIER_CYCLE = 0.05

    def __init__(self) -> None:
        super().__init__()
        self.taps: list[TrafficRecorder] = []

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        self.send_messages([(can_id, data)], remote)

    def send_messages(self, frames: list[tuple[int, bytes]], remote: bool = False) -> None:
        """Send frames back to back; over socketcand in one TCP write (one wake-up of the hub)."""
        if self.bus is None:
            raise DriveConnectionError("CAN bus is closed")
        msgs = [
            can.Message(arbitration_id=i, data=d, is_extended_id=i > 0x7FF, is_remote_frame=remote)
            for i, d in frames
        ]
        with self.send_lock:
            if isinstance(self.bus, SocketCanDaemonBus) and len(msgs) > 1:
                # python-can sends one TCP write per frame; its own encoder, joined, is one write
                self.bus._tcp_send("".join(map(convert_can_message_to_ascii_message, msgs)))
            else:
                for msg in msgs:
                    self.bus.send(msg)
            for tap in self.taps:
                for msg in msgs:
                    tap.on_sent(msg)
        self.check()


class HeartbeatProducer(threading.Thread):
    """Sends the host's heartbeat (NMT state OPERATIONAL) every ``period_s``."""

    def __init__(self, network: canopen.Network, node_id: int, period_s: float) -> None:
        super().__init__(name=f"heartbeat-{node_id}", daemon=True)
        self.network, self.cob_id, self.period_s = network, 0x700 + node_id, period_s
        self.failure: BaseException | None = None
        self._stop_event = threading.Event()

    def run(self) -> None:
        try:
            while True:
                self.network.send_message(self.cob_id, b"\x05")
                if self._stop_event.wait(self.period_s):
                    return
        except BaseException as err:  # surfaced by check() in the host's thread
            self.failure = err

    def check(self) -> None:
        if self.failure is not None:
            raise DriveConnectionError(f"host heartbeat stopped: {self.failure}") from self.failure

    def stop(self) -> None:
        self._stop_event.set()
        self.join(timeout=1.0)


class TrafficRecorder(can.Listener):
    """A python-can :class:`~can.Logger` fed from two threads (sender and notifier).

    The format follows the file suffix (candump ``.log``, ``.blf``, ``.asc``,
    ``.csv``, ...). Sent frames are stamped with the send time and marked as
    transmitted; every write holds one lock, so lines never interleave.
    """

    def __init__(self, path: str) -> None:
        self._logger = can.Logger(path)
        self._lock = threading.Lock()
        self._stopped = False

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            if not self._stopped:
                self._logger.on_message_received(msg)

    def on_sent(self, msg: can.Message) -> None:
        sent = can.Message(
            timestamp=time.time(), arbitration_id=msg.arbitration_id, data=msg.data,
            is_extended_id=msg.is_extended_id, is_remote_frame=msg.is_remote_frame,
            is_rx=False, channel=msg.channel,
        )  # fmt: skip
        self.on_message_received(sent)

    def stop(self) -> None:
        with self._lock:
            if not self._stopped:
                self._stopped = True
                self._logger.stop()
