"""The served CiA 402 drive in a thread of the test process, and a second station on its bus.

:func:`served` runs :func:`servobench.sim_backend.servers.canopen.serve_canopen.serve` in a
thread, on the real socketcand hub over TCP, so that a test can look at the
simulated device while the host driver talks to it through python-can and
canopen, as across processes. :func:`station` is a plain canopen
``RemoteNode`` of the served node (a second host on the bus), and
:func:`raw_bus` a bare python-can bus on the hub, for frames built by hand.
"""

from __future__ import annotations

import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import can
import canopen

from servobench.drivers.canopen.link import load_eds
from servobench.drivers.url import parse_drive_url
from servobench.sim_backend.device import LOCKSTEP, SimulatedDevice, WatchdogThread, device_from_url
from servobench.sim_backend.servers.canopen import serve_canopen
from servobench.sim_backend.servers.serve import split_served_keys

#: The plant most CANopen tests serve.
SIM = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"


@contextmanager
def served(
    sim_url: str = SIM, clock: str = LOCKSTEP, **options: str
) -> Iterator[tuple[SimulatedDevice, str]]:
    """Serve a simulated drive in a thread; yield the device and its drive URL.

    ``sim_url`` may hold the served drive's own keys (factor group, gains);
    ``clock``: ``"lockstep"`` (default here: pure lock-step, exact) or ``"real"``
    (wall-clock time, as ``serve-sim`` serves by default);
    ``options`` are ``serve_canopen.serve`` options (``eds``, ``fault``, ``can``, ``node``).
    """
    plant_url, keys = split_served_keys("canopen", sim_url)
    device = device_from_url(plant_url, clock_mode=clock)
    stop, urls = threading.Event(), queue.Queue()
    errors: list[BaseException] = []

    def run() -> None:
        try:
            serve_canopen.serve(device, stop, urls.put, {"node": "2", "sim_keys": keys, **options})
        except BaseException as err:
            errors.append(err)
            urls.put(None)

    watchdog = WatchdogThread(device)
    watchdog.start()
    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    url = urls.get(timeout=10)
    try:
        if url is None:
            raise errors[0]
        yield device, url
    finally:
        stop.set()
        thread.join(5)
        watchdog.stop()
    assert not thread.is_alive()
    assert not errors, errors


def _hub(url: str) -> dict[str, object]:
    q = parse_drive_url(url)
    return {"interface": "socketcand", "channel": q.host, "host": q.get_str("host"),
            "port": q.get_int("port"), "tcp_tune": True}  # fmt: skip


@contextmanager
def station(url: str, eds: str | None = None) -> Iterator[canopen.RemoteNode]:
    """A second host on the same bus: a plain canopen RemoteNode of the served node.

    For NMT, or SDO while no driver is open: two SDO clients on the default
    channel see each other's responses, as on a real bus.
    """
    q = parse_drive_url(url)
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05  # quick disconnect
    network.connect(**_hub(url))
    try:
        node = network.add_node(q.get_int("node"), load_eds(q.get_int("node"), eds))
        network.send_message(0x77E, b"\x05")  # speak once: the hub forwards to us at once
        yield node
    finally:
        network.disconnect()


@contextmanager
def raw_bus(url: str) -> Iterator[can.BusABC]:
    """A bare python-can bus on the served drive's hub (frames in and out as built)."""
    bus = can.Bus(**_hub(url))
    try:
        bus.send(can.Message(arbitration_id=0x77E, data=b"\x05", is_extended_id=False))
        yield bus
    finally:
        bus.shutdown()


def request(
    bus: can.BusABC, can_id: int, data: bytes, answer_id: int, timeout_s: float = 1.0
) -> bytes:
    """Send one frame and return the data of the first frame with ``answer_id`` that follows."""
    bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        msg = bus.recv(left)
        if msg is not None and msg.arbitration_id == answer_id:
            return bytes(msg.data)
    raise TimeoutError(f"no frame 0x{answer_id:03X} within {timeout_s} s")
