"""``serve-sim --transport canopen``: the simulated drive as a CiA 402 node.

The CAN link comes from ``options["can"]``:

``socketcand`` (default)
    Start a :class:`~servobench.sim_backend.servers.canopen.socketcand_server.SocketcandHub` on
    ``options["host"]`` (127.0.0.1) and ``options["port"]`` (0: a free port).
    The served node sits on the hub *in-process* (a :class:`HubNetwork`), which
    saves a TCP hop and a thread hand-off per frame; hosts connect with
    python-can's ``socketcand`` client, from any process.
``socketcand://HOST:PORT[/CHANNEL]``
    Join an existing hub (or a real socketcand) as a TCP client, e.g. to put
    a second simulated drive with another ``--node`` on the same bus.
``INTERFACE:CHANNEL``
    Any python-can interface: ``socketcan:can0`` for a bench with a real
    CAN adapter, ``virtual:NAME`` for in-process unit tests.

``options["eds"]`` serves that object dictionary instead of the shipped
generic one (``serve-sim --eds FILE``): the node has exactly the EDS's
objects. ``options["sim_keys"]`` holds the served drive's own ``sim://`` keys
as a query string (:data:`SIM_KEYS`: its factor group and position loop
gains; ``serve-sim`` takes them out of ``--sim``).

The announced URL names everything a host needs and no unit scale (the
drive's factor group tells them), with the EDS when one was given, e.g.
``canopen://vcan0?interface=socketcand&host=127.0.0.1&port=40123&node=2``.
"""

from __future__ import annotations

import contextlib
import re
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from urllib.parse import parse_qsl, quote

import can
import canopen

from servobench.drivers.canopen.drive import load_eds
from servobench.errors import DriveConfigError, DriveConnectionError
from servobench.sim_backend.device import SimulatedDevice
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import parse_plan
from servobench.sim_backend.servers.canopen.drive import ServedCiA402Drive
from servobench.sim_backend.servers.canopen.factor import SIM_KEYS
from servobench.sim_backend.servers.canopen.socketcand_server import DEFAULT_CHANNEL, SocketcandHub
from servobench.sim_backend.servers.canopen.wire import CanFrame

#: Housekeeping period of the served drive (fault -> EMCY latency) [s].
POLL_S = 0.005
#: Receive-thread wake-up period of python-can links; stopping waits up to this long [s].
NOTIFIER_CYCLE_S = 0.05
__all__ = ["SIM_KEYS", "drive_url", "link_bus_kwargs", "serve"]


class _PeriodicSend:
    """python-can style periodic task over :meth:`canopen.Network.send_message`."""

    def __init__(self, network: canopen.Network, can_id: int, data: bytes, period_s: float) -> None:
        self._network, self._can_id, self._data = network, can_id, bytes(data or b"")
        self._period_s = period_s
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, name=f"periodic-0x{can_id:X}", daemon=True
        )
        self._thread.start()

    def _run(self) -> None:
        while True:
            self._network.send_message(self._can_id, self._data)
            if self._stop.wait(self._period_s):
                return

    def update(self, data: bytes) -> None:
        self._data = bytes(data)

    def stop(self) -> None:
        self._stop.set()


def _never_muted() -> bool:
    return False


class GatedNetwork(canopen.Network):
    """A canopen network whose controller can go bus-off: while ``gate()`` is true,
    frames are neither received nor sent (see :mod:`servobench.sim_backend.faults.can`)."""

    def __init__(self, gate: Callable[[], bool] = _never_muted) -> None:
        super().__init__()
        self.gate = gate

    def notify(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self.gate():
            super().notify(can_id, data, timestamp)

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if not self.gate():
            super().send_message(can_id, data, remote)

    def send_periodic(
        self, can_id: int, data: bytes, period: float, remote: bool = False
    ) -> _PeriodicSend:
        return _PeriodicSend(self, can_id, data, period)  # through send_message: gated


class HubNetwork(GatedNetwork):
    """A canopen network whose station is an in-process port of a :class:`SocketcandHub`.

    canopen's documented way to plug in a custom backend: frames from the
    hub go to :meth:`notify`, :meth:`send_message` puts frames on the hub.
    """

    def __init__(self, hub: SocketcandHub, gate: Callable[[], bool] = _never_muted) -> None:
        super().__init__(gate)
        self._port = hub.attach(self._receive)

    def _receive(self, frame: CanFrame) -> None:
        self.notify(frame.can_id, bytearray(frame.data), time.time())

    def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
        if remote:
            raise DriveConfigError("the socketcand hub carries no remote frames")
        if not self.gate():
            self._port.send(CanFrame(can_id, bytes(data), can_id > 0x7FF))

    def send_messages(self, messages: list[tuple[int, bytes]]) -> None:
        """Send several frames back to back, in one TCP write per client."""
        if not self.gate():
            self._port.send(
                *(CanFrame(can_id, bytes(data), can_id > 0x7FF) for can_id, data in messages)
            )

    def disconnect(self) -> None:
        self._port.close()


def link_bus_kwargs(link: str) -> dict[str, object] | None:
    """python-can ``Bus`` arguments for ``options["can"]``; ``None`` means "start a hub"."""
    if link == "socketcand":
        return None
    match = re.fullmatch(r"socketcand://([^:/]+):(\d+)(?:/(\S+))?", link)
    if match:
        host, port, channel = match.group(1), int(match.group(2)), match.group(3) or DEFAULT_CHANNEL
        return {
            "interface": "socketcand",
            "channel": channel,
            "host": host,
            "port": port,
            "tcp_tune": True,
        }
    interface, sep, channel = link.partition(":")
    if not (sep and interface and channel) or interface == "socketcand":
        raise DriveConfigError(
            f"--can {link!r}: expected socketcand, socketcand://HOST:PORT[/CHANNEL] or INTERFACE:CHANNEL"
        )
    return {"interface": interface, "channel": channel}


def drive_url(
    interface: str,
    channel: str,
    node_id: int,
    host: str | None = None,
    port: int | None = None,
    eds: str | None = None,
) -> str:
    """The ``canopen://`` URL a host uses to reach the served node (``eds``: its EDS file)."""
    if re.fullmatch(r"[a-z0-9_.-]+", channel):
        url = f"canopen://{channel}?interface={interface}"
    else:  # not a valid URL host (case, slashes): pass it as a query key
        url = f"canopen://?interface={interface}&channel={quote(channel, safe='')}"
    if host is not None:
        url += f"&host={host}&port={port}"
    url += f"&node={node_id}"
    if not eds:
        return url
    where = str(Path(eds).resolve()) if Path(eds).exists() else eds  # a file, or a shipped name
    return f"{url}&eds={quote(where, safe='/')}"


def _connect(
    link: str,
    options: Mapping[str, str],
    node_id: int,
    stack: contextlib.ExitStack,
    gate: Callable[[], bool] = _never_muted,
):
    """``(network, announced URL, hub or None)`` for ``options["can"]``."""
    kwargs = link_bus_kwargs(link)
    eds = options.get("eds") or None
    if kwargs is None:
        host = options.get("host") or "127.0.0.1"
        hub = stack.enter_context(SocketcandHub(host, _int(options, "port", 0)))
        network = HubNetwork(hub, gate)
        stack.callback(network.disconnect)
        h, p = hub.address
        return network, drive_url("socketcand", hub.channel, node_id, h, p, eds), hub
    network = GatedNetwork(gate)
    network.NOTIFIER_CYCLE = NOTIFIER_CYCLE_S
    try:
        network.connect(**kwargs)
    except (can.CanError, OSError, ValueError, ImportError) as err:
        raise DriveConnectionError(f"cannot open CAN link {link!r}: {err}") from err
    stack.callback(network.disconnect)
    url = drive_url(
        str(kwargs["interface"]),
        str(kwargs["channel"]),
        node_id,
        kwargs.get("host"),
        kwargs.get("port"),
        eds,
    )
    return network, url, None


def _int(options: Mapping[str, str], key: str, default: int) -> int:
    text = options.get(key) or str(default)
    try:
        return int(text, 0)
    except ValueError:
        raise DriveConfigError(f"serve-sim option {key}={text!r} is not an integer") from None


def serve(
    device: SimulatedDevice,
    stop: threading.Event,
    announce: Callable[[str], None],
    options: Mapping[str, str],
    injector: FaultInjector | None = None,
) -> None:
    """Serve ``device`` as CiA 402 node ``options["node"]`` until ``stop`` is set.

    Faults come from ``injector``, else from ``options["fault"]``
    (:mod:`servobench.sim_backend.faults.spec`; SYNCs are the cycles).
    """
    node_id = _int(options, "node", 2)
    if not 1 <= node_id <= 127:
        raise DriveConfigError(f"CANopen node id must be 1..127, got {node_id}")
    if injector is None:
        injector = FaultInjector(device, parse_plan(options.get("fault") or "", "canopen"))
    eds = options.get("eds") or None
    try:
        od = load_eds(node_id, eds)
    except (OSError, ValueError, KeyError) as err:
        raise DriveConfigError(f"--eds {eds}: cannot read it as an EDS ({err})") from None
    keys = dict(parse_qsl(options.get("sim_keys") or "", keep_blank_values=True))
    with contextlib.ExitStack() as stack:
        drive = ServedCiA402Drive(device, canopen.LocalNode(node_id, od), injector, keys)
        network, url, hub = _connect(
            options.get("can") or "socketcand", options, node_id, stack, drive.hook.muted
        )
        drive.attach(network)
        stack.callback(drive.close)
        drive.boot()
        announce(url)
        while not stop.wait(POLL_S):
            if hub is not None and hub.failure is not None:
                raise DriveConnectionError(
                    f"socketcand hub stopped: {hub.failure!r}"
                ) from hub.failure
            network.check()
            drive.poll()
