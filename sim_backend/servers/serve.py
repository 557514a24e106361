"""``servobench serve-sim``: serve a simulated drive over a real protocol.

Each transport module ``sim_backend.serve_<name>`` exposes::

    def serve(device, stop, announce, options) -> None

and may define ``SIM_KEYS``, the ``sim://`` keys that configure the served
drive itself rather than its plant (CANopen: its factor group); they are
taken out of the URL and handed over as ``options["sim_keys"]``. ``serve``
starts its server around the :class:`~servobench.sim_backend.device.SimulatedDevice`,
calls ``announce(drive_url)`` exactly once when a client can connect, blocks
until the :class:`threading.Event` ``stop`` is set, then shuts down cleanly.
This module owns what is common: building the device from the ``sim://``
URL in the clock mode asked for (:mod:`servobench.sim_backend.device`:
``real`` by default, the axis moving in wall-clock time whatever the host
does, on a control tick of its own with ``tick_s``; ``lockstep``, clocked
once per cycle while enabled and coasting down in wall-clock time while
nobody polls it), the drive without a time stamp
(:func:`no_timestamp_options`), the fault injector (:mod:`servobench.sim_backend.faults`, from ``options["fault"]``),
the watchdog thread, the state report (``state_file``), SIGINT/SIGTERM
handling and printing the URL as the first line on stdout.
"""

from __future__ import annotations

import importlib
import signal
import sys
import threading
from collections.abc import Callable, Mapping
from urllib.parse import urlencode

from servobench.errors import DriveConfigError
from servobench.sim_backend.device import REAL, SimulatedDevice, WatchdogThread, device_from_url
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.spec import parse_plan
from servobench.sim_backend.faults.state import StateReporter

#: ``--transport`` value -> module implementing ``serve``.
TRANSPORTS: dict[str, str] = {
    "canopen": "servobench.sim_backend.servers.canopen.serve_canopen",
    "modbus-tcp": "servobench.sim_backend.servers.modbus.serve_modbus",
    "modbus-rtu": "servobench.sim_backend.servers.modbus.serve_modbus",
    "serial": "servobench.sim_backend.servers.serial.serve_serial",
    "ethercat": "servobench.sim_backend.servers.ethercat.serve_ethercat",
}

#: What ``--no-timestamp`` serves per transport: the option set, and the value without a time stamp.
NO_TIMESTAMP = {
    "canopen": ("eds", "cia402-nostamp"),  # the generic CiA 402 EDS without 0x1013
    "modbus-tcp": ("map", "servobench-sim-nostamp"),  # servobench-sim without its timestamp register
    "modbus-rtu": ("map", "servobench-sim-nostamp"),
    "ethercat": ("timestamp", "none"),  # no 0x1013 (EDS cia402-nostamp), no 0x10F8
}
#: The option values that serve a time stamp, which ``--no-timestamp`` replaces.
WITH_TIMESTAMP = {"eds": ("",), "map": ("", "servobench-sim"), "timestamp": ("",)}


def no_timestamp_options(transport: str, options: Mapping[str, str]) -> dict[str, str]:
    """``options`` for a drive that gives no time stamp (``serve-sim --no-timestamp``).

    CANopen serves the shipped EDS ``cia402-nostamp`` (no 0x1013), Modbus the
    map ``servobench-sim-nostamp`` (no ``timestamp`` register); the URL the
    transport announces names them. EtherCAT serves a slave without 0x1013 and
    without the timestamp object 0x10F8 (``timestamp=none``; the master still
    reads the DC system time of each frame). The ODrive serial dialect carries no time
    stamp at all: nothing changes. An EDS or map of the user's own is kept
    only if it has no time stamp either, else :class:`DriveConfigError`.
    """
    out = dict(options)
    if transport not in NO_TIMESTAMP:
        return out
    key, value = NO_TIMESTAMP[transport]
    given = out.get(key) or ""
    if given in WITH_TIMESTAMP[key]:
        out[key] = value
    elif _serves_timestamp(key, given):
        flag = "--eds" if key == "eds" else "--map"
        raise DriveConfigError(
            f"--no-timestamp: {flag} {given} has a time stamp "
            f"({'0x1013' if key == 'eds' else 'a timestamp register'}); drop {flag} or --no-timestamp"
        )
    return out


def _serves_timestamp(key: str, given: str) -> bool:
    if key == "map":
        from servobench.drivers.modbus.regmap import load_map

        return "timestamp" in load_map(given)
    from servobench.drivers.canopen.link import load_eds

    return 0x1013 in load_eds(1, given)


#: ``serve(device, stop, announce, options, injector=None)``.
ServeFunction = Callable[..., None]


def load_transport(name: str) -> ServeFunction:
    if name not in TRANSPORTS:
        raise DriveConfigError(
            f"unknown transport {name!r}; choose one of {', '.join(sorted(TRANSPORTS))}"
        )
    module = importlib.import_module(TRANSPORTS[name])
    return module.serve


#: ``sim://`` keys a transport may read that stay in the plant's URL too.
SHARED_KEYS = frozenset({"units"})


def split_served_keys(transport: str, sim_url: str) -> tuple[str, str]:
    """``sim_url`` without the transport's own ``SIM_KEYS``, and those keys as a query string."""
    from servobench.drivers.url import parse_drive_url

    own = getattr(importlib.import_module(TRANSPORTS[transport]), "SIM_KEYS", frozenset())
    parsed = parse_drive_url(sim_url)
    served = {k: v for k, v in parsed.query.items() if k in own}
    if not served:
        return sim_url, ""
    # units= belongs to the plant too (what its signals are in): it stays in both
    plant = urlencode({k: v for k, v in parsed.query.items() if k not in own - SHARED_KEYS})
    return f"{parsed.scheme}://{parsed.host}{parsed.path}" + (
        f"?{plant}" if plant else ""
    ), urlencode(served)


def stop_on_signal(stop: threading.Event) -> Callable[[int, object], None]:
    """A SIGINT/SIGTERM handler that sets ``stop`` from a thread of its own.

    Python runs a handler in the main thread between two bytecodes, which may be inside
    ``stop.wait`` holding ``stop``'s lock (the serving loop waits on it every poll): setting
    it there would wait on that lock forever, and the drive would hang on its way out. The
    thread takes the lock once the main thread lets it go."""

    def handler(signum: int, frame: object) -> None:
        threading.Thread(target=stop.set, name="stop-on-signal", daemon=True).start()

    return handler


def run_server(
    transport: str,
    sim_url: str,
    options: Mapping[str, str] | None = None,
    *,
    stop: threading.Event | None = None,
    announce: Callable[[str], None] | None = None,
    state_file: str | None = None,
    clock_mode: str = REAL,
    tick_s: float | None = None,
    drift_ppm: float | None = None,
) -> SimulatedDevice:
    """Serve ``sim_url`` over ``transport`` until SIGINT/SIGTERM (or ``stop``); return the device.

    ``state_file``: write the drive's state report there (:mod:`servobench.sim_backend.faults.state`).
    ``clock_mode``: ``real`` (default) or ``lockstep`` (:mod:`servobench.sim_backend.device`).
    ``tick_s``: the drive's own control tick [s] (``real`` only); ``None``: the URL's ``tick``.
    ``drift_ppm``: its clock's drift [ppm] (``real`` only); ``None``: the URL's ``drift``.
    """
    serve = load_transport(transport)
    sim_url, served_keys = split_served_keys(transport, sim_url)
    ticked = {} if tick_s is None else {"tick_s": tick_s}
    if drift_ppm is not None:
        ticked["drift_ppm"] = drift_ppm
    device = device_from_url(sim_url, wall_clock=True, clock_mode=clock_mode, **ticked)
    stop = stop or threading.Event()
    opts = {"transport": transport, **(options or {}), "sim_keys": served_keys}
    injector = FaultInjector(device, parse_plan(opts.get("fault") or "", transport))
    reporter = StateReporter(device, injector, state_file) if state_file else None

    def _announce(url: str) -> None:
        print(url, flush=True)

    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, stop_on_signal(stop))
    watchdog = WatchdogThread(device)
    watchdog.start()
    if reporter is not None:
        reporter.start()
    try:
        serve(device, stop, announce or _announce, opts, injector=injector)
    finally:
        watchdog.stop()
        if reporter is not None:
            reporter.finish()  # before the clean-up below: what the host and the faults left
        device.disable()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sys.stdout.flush()
    return device
