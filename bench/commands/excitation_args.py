"""Excitation options shared by ``servobench sidbe`` and ``servobench run``."""

from __future__ import annotations

import argparse

from servobench.bench.procedure import excitation as exc
from servobench.errors import UsageError

#: Choices of ``--loop``.
LOOPS = ("auto", "open", "closed")


def add_excitation_arguments(p: argparse.ArgumentParser) -> None:
    """``--drive``, ``--amplitude``, ``--ratio``, ``--fs``, ``--periods``, ``--period``,
    ``--freqs``, ``--loop``."""
    p.add_argument(
        "--drive", required=True, metavar="URL", help="drive URL, e.g. sim:// or canopen://..."
    )
    p.add_argument(
        "--amplitude",
        type=float,
        default=None,
        metavar="A",
        help=f"level of the binary excitation u1 = ±A [command units] (default {exc.DEFAULT_AMPLITUDE:g} "
        "in open loop; in closed loop chosen to fit the travel; must not exceed the drive's max_u)",
    )
    p.add_argument(
        "--ratio",
        type=float,
        default=exc.DEFAULT_RATIO,
        metavar="R",
        help=f"u2 = R * u1, 0 < R < 1 (default {exc.DEFAULT_RATIO:g})",
    )
    p.add_argument(
        "--fs",
        type=float,
        default=None,
        metavar="HZ",
        help=f"cycle rate [Hz] (default: {exc.DEFAULT_FS_HZ:g}, or what the drive's link carries "
        "with a margin when that is less; a rate beyond the link is refused)",
    )
    p.add_argument(
        "--periods",
        type=int,
        default=exc.DEFAULT_PERIODS,
        metavar="N",
        help=f"excitation periods per run, >= 2; the first is the transient (default {exc.DEFAULT_PERIODS})",
    )
    p.add_argument(
        "--period",
        type=float,
        default=exc.DEFAULT_PERIOD_S,
        metavar="S",
        help=f"length of one excitation period [s] (default {exc.DEFAULT_PERIOD_S:g})",
    )
    p.add_argument(
        "--freqs",
        default=None,
        metavar="F1,F2,...",
        help="excited lines [Hz], multiples of 1/period below Nyquist "
        f"(default: {exc.DEFAULT_LINES} log-spaced lines from 1/period to min(40 Hz, fs/20); "
        "in closed loop from the lowest line the travel allows)",
    )
    p.add_argument(
        "--loop",
        choices=LOOPS,
        default="auto",
        help="excite in open loop, or in closed loop under a slow hold loop that keeps the axis "
        "inside its travel (default auto: closed whenever the drive's xmin/xmax is finite)",
    )


def parse_freqs(text: str | None) -> tuple[float, ...] | None:
    """``"0.25,1,4"`` -> ``(0.25, 1.0, 4.0)``; UsageError for anything else."""
    if text is None:
        return None
    try:
        freqs = tuple(float(f) for f in text.split(",") if f.strip())
    except ValueError:
        raise UsageError(f"--freqs must be comma-separated numbers in Hz, got {text!r}") from None
    if not freqs:
        raise UsageError("--freqs names no frequency")
    return freqs


def link_rate_hz(fs_hz: float | None, drive) -> float:
    """``--fs`` checked against the drive's link, or the link's default rate when it is None."""
    from servobench.drivers.link_budget import drive_rate_hz

    return drive_rate_hz(fs_hz, drive, exc.DEFAULT_FS_HZ)


def design_from_args(args: argparse.Namespace, fs_hz: float) -> exc.ExcitationDesign:
    """Validated excitation design from the parsed options at the cycle rate ``fs_hz`` [Hz]."""
    return exc.make_design(
        exc.DEFAULT_AMPLITUDE if args.amplitude is None else args.amplitude,
        ratio=args.ratio,
        fs_hz=fs_hz,
        periods=args.periods,
        period_s=args.period,
        freqs_hz=parse_freqs(args.freqs),
    )


def check_amplitude(amplitude: float, max_u: float) -> None:
    """UsageError when the amplitude exceeds the drive's command limit."""
    if amplitude > max_u:
        raise UsageError(f"amplitude {amplitude:g} exceeds the drive limit max_u = {max_u:g}")
