"""``serve-sim --transport ethercat --iface IFACE``: the simulated drive as an EtherCAT slave.

The slave (:class:`~.coe_drive.CoeSlave` behind an :class:`~.esc.Esc`) sits on
a raw ``AF_PACKET`` socket bound to ``options["iface"]`` for EtherType
0x88A4, the only frames it reads; it answers each EtherCAT frame by sending
it back processed, with the locally administered bit set in the source
address, as the last slave of a line returns a frame through its port 0.
The interface is used as it is: nothing on it is configured here (the tests
make a veth pair inside a network namespace of their own,
:mod:`servobench.bench.testing.ethercat_link`). A raw socket needs
CAP_NET_RAW (root, or a user namespace of one's own: ``unshare -Urn``).

Faults (``--fault``): ``fault@N`` and ``freeze@N`` act on the drive at
process data cycle N, ``delay@N:MS`` returns that cycle's frame MS ms late.
Drive profiles (``--profile``, ``options["profile"]``: names joined by
commas) emulate real drives' quirks (:mod:`.profiles`).

Between frames, and at least every :data:`POLL_S`, the loop checks the SM
watchdog and runs the SYNC0 events due of a DC-synchronous slave
(:mod:`.coe_drive`), each at the instant of its event. ``options["sim_keys"]`` holds the served drive's own ``sim://``
keys (its factor group and position loop gains, as on CANopen).

The announced URL names the interface a master on this host reaches the
slave through: the peer of a veth pair (the other end of the virtual cable,
as iproute2 shows it), else ``IFACE`` itself (a physical port
cabled to the master's machine): ``ethercat://PEER?slave=1``.
"""

from __future__ import annotations

import contextlib
import re
import select
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Mapping
from urllib.parse import parse_qsl

from servobench.errors import DriveConfigError, DriveConnectionError
from servobench.sim_backend.device import SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import parse_plan
from servobench.sim_backend.servers.canopen.factor import SIM_KEYS
from servobench.sim_backend.servers.ethercat.coe_drive import CoeSlave
from servobench.sim_backend.servers.ethercat.frame import (
    ETHERTYPE_ECAT,
    SOURCE_MAC_MARK,
    Frame,
    FrameError,
    decode_frame,
    encode_frame,
    returned_source,
)
from servobench.sim_backend.servers.ethercat.profiles import parse_profiles

__all__ = ["SIM_KEYS", "open_raw_socket", "serve"]

#: Longest wait for a frame before the watchdog is checked [s].
POLL_S = 0.001
#: Linux socket option: do not deliver frames this socket sent.
PACKET_IGNORE_OUTGOING = 23
PACKET_OUTGOING = 4
SOL_PACKET = 263
_MAX_FRAME = 1518


def open_raw_socket(iface: str) -> socket.socket:
    """A raw socket on ``iface`` for EtherCAT frames.

    Raises
    ------
    DriveConnectionError
        No permission (CAP_NET_RAW) or no such interface.
    """
    try:
        sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETHERTYPE_ECAT))
    except PermissionError:
        raise DriveConnectionError(
            f"cannot open a raw socket for {iface}: EtherCAT needs CAP_NET_RAW "
            "(run as root, or inside 'unshare -Urn' with an interface of that namespace)"
        ) from None
    try:
        with contextlib.suppress(OSError):
            sock.setsockopt(SOL_PACKET, PACKET_IGNORE_OUTGOING, 1)
        sock.bind((iface, ETHERTYPE_ECAT))
    except OSError as err:
        sock.close()
        raise DriveConnectionError(
            f"cannot bind a raw socket to interface {iface!r}: {err.strerror}"
        ) from None
    return sock


def master_side(iface: str) -> str:
    """The interface at the other end of ``iface`` when it is a veth in this namespace, else ``iface``.

    From iproute2's ``ip -o link show dev IFACE`` (``N: IFACE@PEER: <...>``; a peer
    in another namespace shows as ``@ifN`` and is not named).
    """
    try:
        done = subprocess.run(["ip", "-o", "link", "show", "dev", iface],
                              capture_output=True, text=True, timeout=5)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return iface
    match = re.match(r"\d+:\s+([^@:\s]+)@([^:\s]+):", done.stdout)
    if done.returncode != 0 or match is None or re.fullmatch(r"if\d+", match.group(2)):
        return iface
    return match.group(2) if "link/ether" in done.stdout and "veth" in _kind(iface) else iface


def _kind(iface: str) -> str:
    try:
        done = subprocess.run(["ip", "-o", "-d", "link", "show", "dev", iface],
                              capture_output=True, text=True, timeout=5)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return done.stdout


def answer(slave: CoeSlave, raw: bytes, arrival_ns: int | None = None) -> bytes | None:
    """The frame the slave sends back for ``raw``; ``None`` when it is not for it.

    The whole frame is handled at one instant, as it passes an ESC in
    microseconds, ``arrival_ns`` (``time.monotonic_ns()``, default now): the
    device's (:meth:`~servobench.sim_backend.device.SimulatedDevice.instant`)
    and the DC unit's (:meth:`~.esc.Esc.frame_at`); the SYNC0 events due by
    then run first, each at its own instant (:meth:`CoeSlave.sync0_due`).
    """
    arrival_ns = time.monotonic_ns() if arrival_ns is None else arrival_ns
    try:
        frame = decode_frame(raw)
    except FrameError:
        return None
    if frame.src[0] & SOURCE_MAC_MARK:
        return None  # already processed by a slave: a returning frame
    with slave.lock:
        slave.sync0_due(arrival_ns)
        with slave.device.instant(arrival_ns * 1e-9), slave.esc.frame_at(arrival_ns):
            datagrams = tuple(slave.esc.execute(d) for d in frame.datagrams)
    return encode_frame(Frame(frame.dst, returned_source(frame.src), datagrams))


def serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None = None,
) -> None:
    """Serve ``device`` as an EtherCAT CiA 402 slave on ``options["iface"]`` until ``stop``."""
    iface = options.get("iface") or ""
    if not iface:
        raise DriveConfigError("serve-sim --transport ethercat needs --iface IFACE")
    if injector is None:
        injector = FaultInjector(device, parse_plan(options.get("fault") or "", "ethercat"))
    keys = dict(parse_qsl(options.get("sim_keys") or "", keep_blank_values=True))
    profile = parse_profiles(options.get("profile") or "")
    slave = CoeSlave(
        device, injector, keys, timestamp=options.get("timestamp") != "none", profile=profile
    )
    with contextlib.closing(open_raw_socket(iface)) as sock:
        announce(f"ethercat://{master_side(iface)}?slave=1")
        while not stop.is_set():
            ready, _, _ = select.select([sock], [], [], POLL_S)
            if ready:
                raw, address = sock.recvfrom(_MAX_FRAME)
                if len(address) > 2 and address[2] == PACKET_OUTGOING:
                    continue
                reply = answer(slave, raw)
                if reply is not None:
                    if slave.pdo.delay_s:  # --fault delay@N:MS: this cycle's frame comes back late
                        time.sleep(slave.pdo.delay_s)
                        slave.pdo.delay_s = 0.0
                    sock.send(reply)
            with slave.lock:
                slave.sync0_due(time.monotonic_ns())
                slave.esc.poll()
