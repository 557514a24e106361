"""``servobench serve-sim --transport T --sim SIMURL``: serve the simulated drive."""

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
        "--state-file",
        default=None,
        metavar="PATH",
        help="write the drive's state as JSON on every power-state change and at exit",
    )


def run(args: argparse.Namespace) -> int:
    from servobench.errors import UsageError

    if args.eds and args.transport != "canopen":
        raise UsageError(f"--eds applies to --transport canopen only, not {args.transport}")
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
    }
    run_server(args.transport, args.sim, options, state_file=args.state_file)
    return 0
