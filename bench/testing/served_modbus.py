"""The simulated drive served over Modbus in a thread of the test process.

For tests that probe the served drive with raw frames or with other Modbus
stacks and look at the device while they do (its power state, its watchdog
setting); :class:`servobench.bench.testing.served.ServedSim` serves it in a
process of its own instead.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from collections.abc import Iterator

from servobench.sim_backend.device import LOCKSTEP, SimulatedDevice, WatchdogThread, device_from_url
from servobench.sim_backend.servers.modbus import serve_modbus

SIM_URL = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"


@contextlib.contextmanager
def served_modbus(
    transport: str,
    sim_url: str = SIM_URL,
    wall_clock: bool = False,
    clock: str = LOCKSTEP,
    **options: str,
) -> Iterator[tuple[SimulatedDevice, str]]:
    """Serve ``sim_url`` over ``transport`` (``modbus-tcp`` or ``modbus-rtu``); yields (device, URL).

    ``clock``: ``"lockstep"`` (default here; ``wall_clock`` then says whether an
    idle axis coasts in wall-clock time) or ``"real"`` (wall-clock time
    throughout, as ``serve-sim`` serves by default).
    ``options`` are serve options (``map``, ``unit``, ``fault``).
    """
    device = device_from_url(sim_url, wall_clock=wall_clock, clock_mode=clock)
    stop: threading.Event = threading.Event()
    urls: queue.Queue[str | BaseException] = queue.Queue()

    def run() -> None:
        try:
            serve_modbus.serve(
                device, stop, urls.put, {"transport": transport, "port": "0", **options}
            )
        except BaseException as err:  # start-up errors surface in the test
            urls.put(err)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    url = urls.get(timeout=10)
    if isinstance(url, BaseException):
        raise url
    watchdog = WatchdogThread(device)
    watchdog.start()
    try:
        yield device, url
    finally:
        stop.set()
        thread.join(5)
        watchdog.stop()
        if thread.is_alive():
            raise RuntimeError("the served Modbus drive did not stop within 5 s of the test's end")


def host_port(url: str) -> tuple[str, int]:
    """``("127.0.0.1", 5020)`` of a ``modbus+tcp://`` URL."""
    host, port = url.split("://")[1].split("?")[0].rsplit(":", 1)
    return host, int(port)


def rtu_path(url: str) -> str:
    """The device path of a ``modbus+rtu://`` URL."""
    return url.split("://")[1].split("?")[0]
