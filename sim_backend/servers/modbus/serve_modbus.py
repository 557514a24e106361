"""Serve the simulated drive over Modbus TCP or Modbus RTU.

Three layers, as pymodbus has them: the transport (this module: a TCP
listener, or an RTU line on a baud-emulating pty), the framing
(:mod:`servobench.sim_backend.servers.modbus.framing`: MBAP header, RTU CRC)
and the device logic (:mod:`servobench.sim_backend.servers.modbus.pdu`: the
function codes, the exception rules and the register bridge to the
:class:`~servobench.sim_backend.device.SimulatedDevice`). The served register
layout is a :mod:`servobench.drivers.modbus.regmap` map (``servobench-sim`` unless
``--map`` names another).

Unit identifiers
----------------
RTU (Modbus over Serial Line v1.02 §2.2): the drive answers only its own
address. Any other address is another device on the shared line: silence.
Address 0 is a broadcast: write requests are executed, and nothing is ever
answered. A frame whose CRC does not close is discarded, unanswered.

TCP (Messaging on TCP/IP Implementation Guide v1.0b §4.4.1.2): the drive is
addressed by its IP address; unit 0xFF (and 0, which the guide also accepts
for a device addressed directly) mean the drive itself, as does its own
unit id. Any other unit is answered as a gateway with nothing behind it
would: exception 0x0B (gateway target device failed to respond). A frame
whose protocol identifier is not 0 is dropped.

Sessions: a TCP connection opened while no other is open, or the RTU pty
opened by a client, begins a host session
(:meth:`~servobench.sim_backend.device.SimulatedDevice.begin_session`): the
drive clock restarts at 0 and the drive starts clean.

Fault injection (``--fault``, the grammar of :mod:`servobench.sim_backend.faults.spec`;
``N`` counts clocking reads from 1): ``fault@N[:C]``, ``freeze@N``,
``exception@N[:C]`` (``busy@N`` = ``exception@N:6``), ``timeout@N``
(``silence@N``), ``delay@N:MS`` and, on RTU, ``crc@N``; see
:mod:`servobench.sim_backend.faults.modbus`. A refused or unanswered request does not
clock the drive.

RTU runs on a :class:`~servobench.sim_backend.servers.pty_link.PtyLink` that emulates the byte
time of the configured baud rate, so RTU timing measured against the served
drive is that of a real line (without the drive's own turnaround time).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import socketserver
import threading
from collections.abc import Callable, Mapping
from urllib.parse import quote

from servobench.drivers.modbus.regmap import load_map
from servobench.errors import DriveConfigError
from servobench.sim_backend.device import SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.modbus import ModbusFaultHook, NoAnswer
from servobench.sim_backend.faults.spec import FaultPlan, parse_plan
from servobench.sim_backend.servers.modbus.framing import (
    RTU_MIN_BYTES,
    TcpFrame,
    decode_tcp,
    request_length,
    rtu_crc_ok,
    rtu_frame,
    split_rtu,
    tcp_frame_length,
)
from servobench.sim_backend.servers.modbus.pdu import (  # noqa: F401 (re-exported)
    IDENTITY,
    PduHandler,
    RegisterBridge,
)
from servobench.sim_backend.servers.pty_link import PtyLink

DEFAULT_MAP = "servobench-sim"
#: Line rate of the served RTU link [bit/s].
DEFAULT_BAUD = 115200
#: How often the serving loops look at the stop event [s].
STOP_POLL_S = 0.05
#: Modbus RTU inter-frame silence above 19200 baud, fixed by the serial-line spec [s].
T35_FAST_S = 1.75e-3
#: RTU broadcast address (Serial Line v1.02 §2.2).
BROADCAST = 0
#: TCP unit ids that address the device itself (Implementation Guide v1.0b §4.4.1.2).
TCP_SELF_UNITS = (0x00, 0xFF)
#: Gateway exception: target device failed to respond.
GATEWAY_NO_RESPONSE = 0x0B
#: Function codes a broadcast may carry: writes (Serial Line v1.02 §2.1).
WRITE_FUNCTIONS = frozenset({0x05, 0x06, 0x0F, 0x10})


def rtu_frame_gap_s(baud: int) -> float:
    """Modbus RTU t3.5: 3.5 characters of 11 bits, or 1.75 ms above 19200 baud [s]."""
    return T35_FAST_S if baud > 19200 else 3.5 * 11 / baud


def parse_faults(spec: str, transport: str = "modbus-tcp") -> FaultPlan:
    """``"fault@50;busy@80"`` as a :class:`~servobench.sim_backend.faults.spec.FaultPlan`."""
    return parse_plan(spec, transport)


# ------------------------------------------------------------------ RTU
def answer_rtu(handler: PduHandler, unit: int, frame: bytes) -> bytes | None:
    """The drive's RTU answer to one frame, or ``None`` when it must stay silent."""
    if len(frame) < RTU_MIN_BYTES or not rtu_crc_ok(frame):
        return None
    address, pdu = frame[0], frame[1:-2]
    if address == BROADCAST:
        if pdu[0] in WRITE_FUNCTIONS:
            with contextlib.suppress(NoAnswer):
                handler.handle(pdu)  # executed, never answered
        return None
    if address != unit:
        return None  # another device on the line
    try:
        return rtu_frame(unit, handler.handle(pdu))
    except NoAnswer:
        return None


def _incomplete(chunk: bytes) -> bool:
    """True when ``chunk`` ends inside a request: too short to tell its length, or shorter than it."""
    if len(chunk) < 2:
        return True
    short_header = {0x0F: 7, 0x10: 7, 0x17: 11}.get(chunk[1])
    if short_header is not None and len(chunk) < short_header:
        return True
    n = request_length(chunk)
    return n is not None and len(chunk) < n


def _serve_rtu(handler: PduHandler, unit: int, fd: int, stop: threading.Event, gap_s: float = 0.0) -> None:
    """Answer RTU frames arriving on ``fd`` until ``stop`` is set.

    A burst that ends inside a request whose length its function code gives
    (the line delivered it in two reads, as a loaded machine does) waits up
    to a frame gap ``gap_s`` for the rest, as a slave's receiver does: a
    frame cut in two would otherwise fail its CRC and go unanswered.
    """
    chunk = b""
    while not stop.is_set():
        wait_s = STOP_POLL_S if not chunk else max(gap_s, 1e-3)
        ready, _, _ = select.select([fd], [], [], wait_s)
        if ready:
            try:
                chunk += os.read(fd, 4096)
            except (BlockingIOError, InterruptedError):
                continue
            if _incomplete(chunk):
                continue  # the rest of this request is on its way
        if not chunk:
            continue
        chunk, burst = b"", chunk
        for frame in split_rtu(burst):
            reply = answer_rtu(handler, unit, frame)
            if reply is not None:
                with contextlib.suppress(BlockingIOError):
                    os.write(fd, reply)


# ------------------------------------------------------------------ TCP
def answer_tcp(handler: PduHandler, unit: int, frame: TcpFrame) -> TcpFrame | None:
    """The drive's TCP answer to one request, or ``None`` to drop it."""
    if frame.protocol != 0 or not frame.pdu:
        return None
    if frame.unit != unit and frame.unit not in TCP_SELF_UNITS:
        pdu = bytes([frame.pdu[0] | 0x80, GATEWAY_NO_RESPONSE])
        return TcpFrame(frame.transaction, 0, frame.unit, pdu)
    try:
        return TcpFrame(frame.transaction, 0, frame.unit, handler.handle(frame.pdu))
    except NoAnswer:
        return None


class _TcpServer(socketserver.ThreadingTCPServer):
    daemon_threads = True
    allow_reuse_address = True

    def __init__(self, address: tuple[str, int], handler: PduHandler, unit: int) -> None:
        self.pdu_handler, self.unit = handler, unit
        self.sessions_lock = threading.Lock()
        self.connections: set[socket.socket] = set()
        super().__init__(address, _TcpConnection)

    def close_all(self) -> None:
        """Stop listening and drop every client connection (the drive is switched off)."""
        self.shutdown()
        self.server_close()
        with self.sessions_lock:
            for sock in list(self.connections):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)


class _TcpConnection(socketserver.BaseRequestHandler):
    """One client connection: frames in, answers out, until the client closes."""

    server: _TcpServer

    def setup(self) -> None:
        self.request.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        with self.server.sessions_lock:
            self.server.connections.add(self.request)
            if len(self.server.connections) == 1:
                self.server.pdu_handler.bridge.device.begin_session()

    def finish(self) -> None:
        with self.server.sessions_lock:
            self.server.connections.discard(self.request)

    def handle(self) -> None:
        buf = b""
        while True:
            try:
                data = self.request.recv(4096)
            except OSError:
                return
            if not data:
                return
            buf += data
            while (n := tcp_frame_length(buf)) is not None and len(buf) >= n:
                frame, buf = decode_tcp(buf[:n]), buf[n:]
                reply = answer_tcp(self.server.pdu_handler, self.server.unit, frame)
                if reply is not None:
                    try:
                        self.request.sendall(reply.encode())
                    except OSError:
                        return


# ---------------------------------------------------------------- serving
def _url_tail(unit: int, map_name: str) -> str:
    return f"unit={unit}&map={quote(map_name, safe='')}"


def serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None = None,
) -> None:
    """Serve ``device`` (``options["transport"]``: modbus-tcp or modbus-rtu) until ``stop`` is set.

    Faults come from ``injector``, else from ``options["fault"]``.
    """
    map_name = options.get("map") or DEFAULT_MAP
    unit = int(options.get("unit") or 1)
    transport = options.get("transport", "modbus-tcp")
    if transport not in ("modbus-tcp", "modbus-rtu"):
        raise DriveConfigError(f"serve_modbus cannot serve transport {transport!r}")
    if not 1 <= unit <= 247:
        raise DriveConfigError(f"unit {unit} is not a Modbus device address (1..247)")
    if injector is None:
        injector = FaultInjector(device, parse_plan(options.get("fault") or "", transport))
    hook = ModbusFaultHook()
    bridge = RegisterBridge(device, load_map(map_name), injector, hook)
    handler = PduHandler(bridge, serial_line=transport == "modbus-rtu")
    if transport == "modbus-tcp":
        host = options.get("host") or "127.0.0.1"
        server = _TcpServer((host, int(options.get("port") or 0)), handler, unit)
        thread = threading.Thread(
            target=server.serve_forever, args=(STOP_POLL_S,), name="modbus-tcp", daemon=True
        )
        thread.start()
        try:
            announce(f"modbus+tcp://{host}:{server.server_address[1]}?{_url_tail(unit, map_name)}")
            stop.wait()
        finally:
            server.close_all()
        return
    baud = int(options.get("baud") or DEFAULT_BAUD)
    link = PtyLink(baud=baud, frame_gap_s=rtu_frame_gap_s(baud), on_open=device.begin_session)
    link.start()
    hook.link = link
    fd = os.open(link.b_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        announce(f"modbus+rtu://{link.a_path}?baud={baud}&{_url_tail(unit, map_name)}")
        _serve_rtu(handler, unit, fd, stop, rtu_frame_gap_s(baud))
    finally:
        os.close(fd)
        link.close()
