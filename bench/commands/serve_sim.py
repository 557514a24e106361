"""``servobench serve-sim --transport T --sim SIMURL``: serve the simulated drive.

The first line on stdout is the drive URL (a contract); ``--rt-priority``
says on stderr what priority was obtained. ``--tick S`` (or the URL's
``tick=S``; the option wins) gives the drive a control tick of its own
(:mod:`servobench.sim_backend.device`), ``--drift PPM`` (or ``drift=PPM``) a
clock that drifts against the host's; ``--state-file`` reports its timing
under ``"tick"``.
"""

from __future__ import annotations

import argparse

from servobench.sim_backend.servers.serve import TRANSPORTS, run_server


def add_arguments(p: argparse.ArgumentParser) -> None:
    from servobench.sim_backend.faults.spec import grammar_help

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = grammar_help()
    p.add_argument("--transport", required=True, choices=sorted(TRANSPORTS))
    p.add_argument("--sim", default="sim://", metavar="SIMURL", help="plant, as a sim:// URL")
    p.add_argument("--host", default="127.0.0.1", help="listen address for TCP transports")
    p.add_argument("--port", type=int, default=0, help="TCP port (0: pick a free one)")
    p.add_argument("--node", type=int, default=2, help="CANopen node id")
    p.add_argument("--iface", default="", help="EtherCAT: network interface to serve on")
    p.add_argument("--unit", type=int, default=1, help="Modbus unit id")
    p.add_argument("--baud", type=int, default=115200, help="baud rate emulated on pty links")
    p.add_argument("--map", default="servobench-sim", help="Modbus register map name or file")
    p.add_argument("--dialect", default="odrive", help="serial dialect name or file")
    p.add_argument(
        "--firmware",
        default="",
        metavar="VERSION",
        help="serial: firmware release the dialect's firmware model emulates (ODrive 0.5.1-0.5.6; "
        "default the latest)",
    )
    p.add_argument(
        "--can", default="socketcand", help="CAN link to serve on: socketcand|slcan|socketcan:IFACE"
    )
    p.add_argument(
        "--eds",
        default=None,
        metavar="FILE",
        help="CANopen: serve the drive with this object dictionary (EDS) instead of the generic one",
    )
    p.add_argument(
        "--fault",
        action="append",
        default=[],
        metavar="SPEC",
        help="inject a fault, e.g. drop@120 or delay@50:30 (repeatable; see below)",
    )
    p.add_argument(
        "--clock",
        choices=("real", "lockstep"),
        default=None,
        help="real: the axis moves in wall-clock time and samples when the SYNC or read arrives, "
        "time stamps from its free-running clock (default, or the --sim URL's clock=); "
        "lockstep: one cycle per SYNC/read, exact, for algorithm tests",
    )
    p.add_argument(
        "--tick",
        type=float,
        default=None,
        metavar="S",
        help="--clock real: the drive's own control tick [s], asynchronous to the host from a "
        "random phase: it samples at its ticks and a command acts from the next tick (0: none, "
        "sample and act at each request; default the --sim URL's tick=, else 0)",
    )
    p.add_argument(
        "--drift",
        type=float,
        default=None,
        metavar="PPM",
        help="--clock real: the drive clock runs PPM parts per million fast (negative: slow) "
        "against the host's, as a real drive's crystal does: its ticks and time stamps drift "
        "against the host's cycle (default the --sim URL's drift=, else 0)",
    )
    p.add_argument(
        "--no-timestamp",
        action="store_true",
        help="serve a drive that gives no time stamp: CANopen without 0x1013 (EDS cia402-nostamp), "
        "Modbus without the timestamp register (map servobench-sim-nostamp), "
        "EtherCAT without 0x1013 and the timestamp object 0x10F8",
    )
    p.add_argument(
        "--profile",
        action="append",
        default=[],
        metavar="NAME[,NAME...]",
        help="EtherCAT: emulate real drives' quirks (repeatable): no-cst, cycle-time-ro, "
        "no-complete-access, ca-stored-wrong, quick-stop=N (0x605A, 0..8), no-quick-stop",
    )
    p.add_argument(
        "--rt-priority",
        type=int,
        default=None,
        metavar="N",
        help="ask for real-time priority SCHED_FIFO N (1-99) for the served drive, as a drive with "
        "its own processor, else the best nice level; what was obtained goes to stderr",
    )
    p.add_argument(
        "--state-file",
        default=None,
        metavar="PATH",
        help="write the drive's state as JSON on every power-state change and at exit",
    )


def run(args: argparse.Namespace) -> int:
    import math
    import sys

    from servobench.drivers.url import parse_drive_url
    from servobench.errors import UsageError
    from servobench.sim_backend.device import REAL, clock_mode_from_url
    from servobench.sim_backend.drive_tick import check_drift, drift_from_url, tick_from_url
    from servobench.sim_backend.servers.rt_priority import FIFO_MAX, FIFO_MIN, request_priority
    from servobench.sim_backend.servers.serve import no_timestamp_options

    if args.eds and args.transport != "canopen":
        raise UsageError(f"--eds applies to --transport canopen only, not {args.transport}")
    profile = ",".join(args.profile)
    if profile and args.transport != "ethercat":
        raise UsageError(f"--profile applies to --transport ethercat only, not {args.transport}")
    if profile:
        from servobench.sim_backend.servers.ethercat.profiles import parse_profiles

        parse_profiles(profile)  # an unknown name is a usage error before anything starts
    if args.rt_priority is not None and not FIFO_MIN <= args.rt_priority <= FIFO_MAX:
        raise UsageError(f"--rt-priority must be {FIFO_MIN}..{FIFO_MAX}, got {args.rt_priority}")
    sim = parse_drive_url(args.sim)
    clock_mode = args.clock or clock_mode_from_url(sim, default="real")
    if args.tick is not None and not (math.isfinite(args.tick) and args.tick >= 0):
        raise UsageError(f"--tick must be a finite number of seconds >= 0, got {args.tick}")
    tick_s = args.tick if args.tick is not None else tick_from_url(sim)
    if tick_s > 0 and clock_mode != REAL:
        raise UsageError(f"--tick / tick= {tick_s:g} needs --clock real, not {clock_mode}")
    drift_ppm = check_drift(args.drift, "--drift") if args.drift is not None else drift_from_url(sim)
    if drift_ppm != 0 and clock_mode != REAL:
        raise UsageError(f"--drift / drift= {drift_ppm:g} needs --clock real, not {clock_mode}")
    options = {
        "host": args.host,
        "port": str(args.port),
        "node": str(args.node),
        "unit": str(args.unit),
        "baud": str(args.baud),
        "map": args.map,
        "dialect": args.dialect,
        "firmware": args.firmware,
        "can": args.can,
        "eds": args.eds or "",
        "iface": args.iface,
        "fault": ";".join(args.fault),
        "profile": profile,
    }
    if args.no_timestamp:
        options = no_timestamp_options(args.transport, options)
    if args.rt_priority is not None:  # before any thread starts: they inherit it
        print(f"serve-sim: {request_priority(args.rt_priority).describe()}", file=sys.stderr, flush=True)
    run_server(
        args.transport,
        args.sim,
        options,
        state_file=args.state_file,
        clock_mode=clock_mode,
        tick_s=tick_s,
        drift_ppm=drift_ppm,
    )
    return 0
