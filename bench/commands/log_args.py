"""The log options shared by ``identify``, ``diagnose`` and ``validate``: LOG, ``--columns``, ``--mat-map``."""

from __future__ import annotations

import argparse

MAP_HELP = (
    "which column (CSV) or variable (.mat) holds each signal, e.g. "
    "t=Time,u=Input*35.15,v=Velocity,x=Position (a factor may be a number or a name)"
)


def add_log_arguments(p: argparse.ArgumentParser) -> None:
    """LOG and its two mapping options (one mapping: the names say which file kind it is for)."""
    p.add_argument(
        "log",
        metavar="LOG",
        help="servobench CSV log, CSV of another tool (',', ';' or tab; decimal commas), "
        "or MATLAB .mat file",
    )
    p.add_argument("--columns", metavar="MAP", default=None, help=MAP_HELP)
    p.add_argument(
        "--mat-map",
        metavar="MAP",
        default=None,
        help="the same mapping for .mat variables, e.g. t=t,u=vir*gtau,x=qm "
        "(without it a .mat file lists the variables it holds)",
    )

