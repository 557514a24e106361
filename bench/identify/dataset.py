"""Turn an :class:`~servobench.bench.logio.ExperimentLog` into analysis-ready segments.

Each run becomes a :class:`Segment` holding the command ``u``, the velocity
``v`` (measured, or derived from position with a zero-phase filter), the
sample interval (nominal ``1/fs``, or per interval from ``t`` when the time
stamps jitter by more than :data:`JITTER_RTOL`), and the excitation design if
the log's metadata names one. The checks that make identification
meaningless (no excitation, no motion, too short) raise
:class:`~servobench.errors.IdentificationError` here, once.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.excitation import ExcitationDesign, design_from_metadata
from servobench.bench.identify.derivative import DerivedMotion, differentiate_position
from servobench.bench.logio import ExperimentLog
from servobench.errors import IdentificationError

#: Relative spread of the sample intervals above which per-interval dt is used.
JITTER_RTOL = 1e-3
#: Fewest samples a run must have.
MIN_SAMPLES = 20


@dataclass(frozen=True)
class Segment:
    """One run, ready for identification; arrays of shape ``(n,)``.

    Attributes
    ----------
    run : int
        Run number (1 = u1, 2 = u2).
    t : ndarray
        Sample times [s].
    u : ndarray
        Command [command units], held over ``[t_k, t_{k+1})``.
    v : ndarray
        Velocity [units/s] at ``t_k`` (measured, or derived when ``motion`` is set).
    dt_s : ndarray or None
        Per-interval sample time [s], shape ``(n - 1,)``, or None for the nominal ``1/fs``.
    motion : DerivedMotion or None
        Filtered position, velocity and acceleration when ``v`` was derived from position.
    x : ndarray or None
        Logged position [units], if any.
    """

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray
    dt_s: np.ndarray | None = None
    motion: DerivedMotion | None = None
    x: np.ndarray | None = None

    @property
    def derived(self) -> bool:
        return self.motion is not None

    def __len__(self) -> int:
        return int(self.u.shape[0])

    def head(self, n: int) -> Segment:
        """The first ``n`` samples."""
        motion = self.motion
        if motion is not None:
            motion = DerivedMotion(
                motion.x[:n], motion.v[:n], motion.a[:n], motion.cutoff_hz, motion.method
            )
        dt = None if self.dt_s is None else self.dt_s[: max(0, n - 1)]
        x = None if self.x is None else self.x[:n]
        return Segment(self.run, self.t[:n], self.u[:n], self.v[:n], dt, motion, x)


@dataclass(frozen=True)
class Dataset:
    """Segments of one log plus what is known about the experiment.

    Attributes
    ----------
    segments : tuple of Segment
    fs_hz : float
        Nominal sample rate [Hz].
    design : ExcitationDesign or None
        The periodic excitation, when the metadata describes it.
    source : str
        Where the data came from (file name).
    notes : tuple of str
        Facts worth reporting (derived velocity, irregular sampling).
    closed_loop : bool or None
        From the ``loop`` metadata key (``open``/``closed ...``); None when unknown.
    """

    segments: tuple[Segment, ...]
    fs_hz: float
    design: ExcitationDesign | None = None
    source: str = ""
    notes: tuple[str, ...] = ()
    closed_loop: bool | None = None

    @property
    def dt_s(self) -> float:
        return 1.0 / self.fs_hz

    @property
    def derived(self) -> bool:
        return any(s.derived for s in self.segments)

    @property
    def jittered(self) -> bool:
        return any(s.dt_s is not None for s in self.segments)

    def run(self, number: int) -> Segment:
        for s in self.segments:
            if s.run == number:
                return s
        raise IdentificationError(f"{self.source or 'log'} has no run {number}")

    def has_pair(self) -> bool:
        """True when runs 1 and 2 exist (the SIDBE u1/u2 pair)."""
        numbers = {s.run for s in self.segments}
        return {1, 2} <= numbers

    def periodic_periods(self) -> int:
        """Whole periods in the shortest run (0 without a periodic design)."""
        if self.design is None:
            return 0
        n = self.design.samples_per_period
        return min(len(s) for s in self.segments) // n

    def first_periods(self, periods: int) -> Dataset:
        """Each run cut to its first ``periods`` periods (the design updated to match)."""
        if self.design is None:
            raise IdentificationError("the log describes no periodic excitation")
        n = periods * self.design.samples_per_period
        return replace(
            self,
            segments=tuple(s.head(n) for s in self.segments),
            design=self.design.with_periods(periods),
        )


def prepare(
    log: ExperimentLog,
    *,
    velocity_cutoff_hz: float | None = None,
    derivative_method: str = "butter",
) -> Dataset:
    """Build a :class:`Dataset` from a log.

    Parameters
    ----------
    log : ExperimentLog
    velocity_cutoff_hz : float, optional
        Cut-off of the position filter when velocity must be derived [Hz].
    derivative_method : {"butter", "savgol"}

    Raises
    ------
    IdentificationError
        A run is too short, ``u`` is zero throughout, or nothing moves.
    """
    fs = float(log.fs_hz)
    notes: list[str] = []
    if not log.complete:
        notes.append(
            "the log is incomplete (no 'status = complete' trailer): the run was cut short"
        )
    segments: list[Segment] = []
    for r in log.runs:
        if len(r) < MIN_SAMPLES:
            raise IdentificationError(
                f"run {r.run} has {len(r)} samples; at least {MIN_SAMPLES} are needed"
            )
        t = np.asarray(r.t, dtype=float)
        dt = np.diff(t)
        dt_s = None
        nominal = 1.0 / fs
        if dt.std() > JITTER_RTOL * dt.mean() or abs(np.median(dt) - nominal) > 1e-2 * nominal:
            dt_s = dt
            note = "irregular time stamps: per-sample intervals from t are used"
            if note not in notes:
                notes.append(note)
        motion = None
        if r.v is not None:
            v = np.asarray(r.v, dtype=float)
        else:
            motion = differentiate_position(
                r.x, fs, velocity_cutoff_hz, derivative_method, t=None if dt_s is None else t
            )
            v = motion.v
            note = (
                f"velocity derived from position ({derivative_method}, zero-phase, "
                f"cut-off {motion.cutoff_hz:.4g} Hz)"
            )
            if note not in notes:
                notes.append(note)
        x = None if r.x is None else np.asarray(r.x, dtype=float)
        segments.append(Segment(r.run, t, np.asarray(r.u, dtype=float), v, dt_s, motion, x))
    if not any(np.any(s.u != 0) for s in segments):
        raise IdentificationError("no excitation: the command u is zero throughout the log")
    if not any(_moves(s) for s in segments):
        raise IdentificationError("no motion in the data: velocity (or position) never changes")
    design = design_from_metadata(log.metadata, fs, log.source)
    if design is not None and min(len(s) for s in segments) < 2 * design.samples_per_period:
        notes.append("fewer than two excitation periods per run: periodic processing disabled")
        design = None
    elif design is not None:
        periods = min(len(s) for s in segments) // design.samples_per_period
        if periods != design.periods:
            design = design.with_periods(periods)
    loop = log.metadata.get("loop", "").strip().lower()
    closed = True if loop.startswith("closed") else False if loop.startswith("open") else None
    return Dataset(tuple(segments), fs, design, log.source, tuple(notes), closed)


def _moves(s: Segment) -> bool:
    if s.motion is not None:
        x = s.motion.x
        return bool(np.ptp(x) > 0 and np.any(s.v != 0))
    return bool(np.any(s.v != 0) and np.ptp(s.v) > 0)
