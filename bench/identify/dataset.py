"""The prepared log: analysis-ready runs, shared by identification and diagnosis.

Each run of an :class:`~servobench.bench.log.io.ExperimentLog` becomes a
:class:`Segment` holding the command ``u``, the velocity ``v`` (measured, or
derived from position with a zero-phase filter), the sample interval
(nominal ``1/fs``, or per interval from ``t`` when the time stamps jitter by
more than :data:`JITTER_RTOL`), and the excitation design if the log's
metadata names one. The checks that make an analysis meaningless (too short,
nothing moves, no excitation) raise
:class:`~servobench.errors.IdentificationError` here, once.

A log whose instants are the drive's own time stamps (``clock_source =
drive``) and that holds the host's instants beside them (``t_host``) has
each run's stamps taken onto the host's seconds where the drive's clock
drifts against the host's measurably (:mod:`~servobench.bench.identify.drive_rate`):
a model identified with stamps and one identified without them then share
one time base, and a drive's fast crystal no longer makes ``M`` that much
large. Every run's rate is kept in :attr:`Dataset.drive_rates`, mapped or
not: :meth:`Dataset.time_base_error_ppm` is what the time base may still be
off by.

Where a simulation starts from the data, :func:`initial_velocity` gives its
initial velocity by one rule: the velocity at that sample, taken as rest when
it lies within :data:`REST_SIGMAS` noise deviations of zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from servobench.bench.identify.derivative import (
    DerivedMotion,
    differentiate_position,
    lowpass,
    settle_samples,
)
from servobench.bench.identify.drive_rate import DriveRate, drive_rate, onto_host_seconds
from servobench.bench.log.io import ExperimentLog, RunData
from servobench.bench.procedure.excitation import ExcitationDesign, design_from_metadata
from servobench.errors import IdentificationError
from servobench.units import SignalUnits

#: Relative spread of the sample intervals above which per-interval dt is used.
JITTER_RTOL = 1e-3
#: Fewest samples a run must have.
MIN_SAMPLES = 20
#: The log column of the instant each row's command took force, where the drive says it
#: (:meth:`~servobench.drivers.base.Drive.reports_action_instant`), and the share of a cycle
#: by which it must lie before its row's instant to count as moved.
ACT_COLUMN = "t_act"
ACT_TOLERANCE = 1e-3
#: Fewest sample pairs holding a command change for the pairs to show the drive's delay
#: (:meth:`Dataset.switch_pairs`); with fewer, the model's simulation shows it.
MIN_SWITCH_PAIRS = 20
#: A row's bracket (``t_unc``) wider than the log's median by more than this share of the cycle,
#: and by :data:`STALL_EXCESS_SPREADS` of the brackets' spread, is an exchange the host stalled in
#: (:meth:`Segment.stalled_rows`).
STALL_EXCESS_SHARE = 0.1
STALL_EXCESS_SPREADS = 5.0
#: A command change sent in a stalled exchange sets aside the samples it may have moved by more
#: than this share of the velocity's rms (:meth:`Segment.after_stalled_commands`).
STALL_MOVE_SHARE = 1e-3
#: Initial velocities within this many noise deviations of zero are taken as rest.
REST_SIGMAS = 3.0


@dataclass(frozen=True)
class Segment:
    """One run, ready for analysis; arrays of shape ``(n,)``.

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
    fs_hz : float
        Nominal sample rate [Hz].
    dt_s : ndarray or None
        Per-interval sample time [s], shape ``(n - 1,)``, or None for the nominal ``1/fs``.
    motion : DerivedMotion or None
        Filtered position, velocity and acceleration when ``v`` was derived from position.
    x : ndarray or None
        Logged position [units], if any.
    u_exc : ndarray or None
        Closed loop: the excitation [command units] (``u`` is then the total
        command, the hold loop's included); the closed-loop estimators' instrument.
    x_ref : ndarray or None
        Closed loop: the position the hold loop held [units].
    t_unc : ndarray or None
        Timing uncertainty of each sample [s]: the half-width of the interval
        known to hold its instant (the log's ``t_unc`` column of a real-time
        run without drive time stamps); None when the log has none.
    act_offset_s : ndarray or None
        Each command's own shift [s] of the instant it acts from, on top of the
        model's action delay (zero mean; see :mod:`~servobench.bench.identify.delay`):
        set where the drive's tick was located on the host's clock and its commands
        and samples travel in separate requests, or where the drive said a
        command took force before its row's sample (the log's ``t_act``: an
        EtherCAT sample read a cycle late, negative offsets of whole cycles
        on the rows concerned, 0 elsewhere); None: every command acts the
        delay after its row's instant.
    """

    run: int
    t: np.ndarray
    u: np.ndarray
    v: np.ndarray
    fs_hz: float
    dt_s: np.ndarray | None = None
    motion: DerivedMotion | None = None
    x: np.ndarray | None = None
    u_exc: np.ndarray | None = None
    x_ref: np.ndarray | None = None
    t_unc: np.ndarray | None = None
    act_offset_s: np.ndarray | None = None

    @property
    def derived(self) -> bool:
        return self.motion is not None

    def __len__(self) -> int:
        return int(self.u.shape[0])

    @cached_property
    def v_f(self) -> np.ndarray:
        """Low-passed velocity [units/s]: the derived velocity as it is (already filtered),
        a measured one through :func:`~servobench.bench.identify.derivative.lowpass`."""
        return self.v if self.derived else lowpass(self.v, self.fs_hz)

    @cached_property
    def position(self) -> np.ndarray:
        """Position [units]: as logged, or the velocity integrated (trapezoids) from 0."""
        if self.x is not None:
            return self.x
        mean_v = 0.5 * (self.v[1:] + self.v[:-1])
        steps = mean_v / self.fs_hz if self.dt_s is None else mean_v * self.dt_s
        return np.concatenate([[0.0], np.cumsum(steps)])

    def stalled_rows(self, dt_s: float) -> np.ndarray:
        """The rows of exchanges the host stalled in (bool, shape ``(n,)``): a bracket (``t_unc``)
        wider than the log's median by more than :data:`STALL_EXCESS_SHARE` of the cycle ``dt_s``
        [s] and :data:`STALL_EXCESS_SPREADS` of the brackets' spread. No row where the log has no
        ``t_unc``."""
        return _stalled(self.bracket_excess_s(), dt_s)

    def bracket_excess_s(self) -> np.ndarray:
        """Each row's bracket (``t_unc``) beyond the log's median [s], shape ``(n,)`` (zeros without
        ``t_unc``): how much longer than usual its exchange took, the host stalled in it."""
        if self.t_unc is None:
            return np.zeros(len(self))
        unc = np.asarray(self.t_unc, dtype=float)
        return unc - float(np.median(unc))

    def after_stalled_commands(self, dt_s: float, mass: float, damping: float) -> np.ndarray:
        """The samples a command change sent in a stalled exchange may have moved (bool, shape
        ``(n,)``): after each of :meth:`stalled_rows` whose command changed (the request went out
        somewhere in its bracket, so where the command acted is unknown), every sample while what
        that can move it, ``min(|du| / B, |du| / M * excess) * exp(-(t - t_k) B / M)`` (a step
        ``du`` shifted by the bracket's excess over the log's median, for mass ``mass`` and
        damping ``damping``), exceeds :data:`STALL_MOVE_SHARE` of the velocity's rms; the next
        sample at least."""
        excess = self.bracket_excess_s()
        return self._after(_stalled(excess, dt_s), excess, mass, damping)

    def stalled_samples(self, dt_s: float, mass: float, damping: float) -> np.ndarray:
        """:meth:`stalled_rows` or :meth:`after_stalled_commands` (bool, shape ``(n,)``): the
        samples no grid or fit can be judged on, the brackets read once (a grid search asks this
        of every trial grid's log)."""
        excess = self.bracket_excess_s()
        stalled = _stalled(excess, dt_s)
        return stalled | self._after(stalled, excess, mass, damping)

    def _after(self, stalled: np.ndarray, excess: np.ndarray, mass: float, damping: float) -> np.ndarray:
        out = np.zeros(len(self), dtype=bool)
        if not stalled[1:-1].any() or not (mass > 0 and damping > 0):
            return out
        level = STALL_MOVE_SHARE * float(np.sqrt(np.mean(self.v**2)))
        tau = mass / damping
        du = np.abs(np.diff(self.u))  # row k's change against row k-1's
        for k in np.flatnonzero(stalled[1:-1]) + 1:
            if du[k - 1] == 0:
                continue
            reach = min(du[k - 1] / damping, du[k - 1] / mass * excess[k])
            span = tau * math.log(reach / level) if level > 0 and reach > level else 0.0
            end = int(np.searchsorted(self.t, self.t[k] + span, side="right"))
            out[k + 1 : max(end, k + 2)] = True
        return out

    def head(self, n: int) -> Segment:
        """The first ``n`` samples."""
        motion = self.motion
        if motion is not None:
            motion = DerivedMotion(
                motion.x[:n], motion.v[:n], motion.a[:n], motion.cutoff_hz, motion.method
            )
        dt = None if self.dt_s is None else self.dt_s[: max(0, n - 1)]
        x, u_exc, x_ref, t_unc, offsets = (
            None if a is None else a[:n]
            for a in (self.x, self.u_exc, self.x_ref, self.t_unc, self.act_offset_s)
        )
        return Segment(
            self.run, self.t[:n], self.u[:n], self.v[:n], self.fs_hz, dt, motion, x, u_exc, x_ref,
            t_unc, offsets,
        )  # fmt: skip


def _stalled(excess: np.ndarray, dt_s: float) -> np.ndarray:
    """:meth:`Segment.stalled_rows` from the rows' bracket excess [s]."""
    if excess.size < 2:
        return np.zeros(excess.size, dtype=bool)
    spread = 1.4826 * float(np.median(np.abs(excess)))
    return (excess > STALL_EXCESS_SHARE * dt_s) & (excess > STALL_EXCESS_SPREADS * spread)


def initial_velocity(segment: Segment, noise_std: float, k: int = 0) -> float:
    """Velocity [units/s] to start a simulation from at sample ``k``: 0 when the axis rests there.

    The velocity at ``k`` is taken as rest when it lies within ``REST_SIGMAS *
    noise_std`` of zero. The threshold is the noise, not a share of the
    velocity's range: a log that starts at rest within the noise starts the
    model at rest, and one that starts in motion, however slowly, starts it
    in motion (exactly so for noise-free data).

    The velocity at ``k`` is ``v[k]``, except where ``v`` was derived from
    position and ``k`` lies within the filter's edge transient: there it is
    extrapolated from the next two position increments,
    ``(1.5 (x1 - x0) - 0.5 (x2 - x1)) / dt``.

    Parameters
    ----------
    segment : Segment
    noise_std : float
        Noise [units/s] of ``v`` (0 for derived or noise-free velocity).
    k : int
        Sample index.
    """
    v0 = float(segment.v[k])
    motion = segment.motion
    if motion is not None and segment.x is not None and k + 2 < len(segment):
        edge = settle_samples(segment.fs_hz, motion.cutoff_hz)
        if k < edge or k >= len(segment) - edge:
            x, t = segment.x, segment.t
            v0 = float(
                1.5 * (x[k + 1] - x[k]) / (t[k + 1] - t[k])
                - 0.5 * (x[k + 2] - x[k + 1]) / (t[k + 2] - t[k + 1])
            )
    return 0.0 if abs(v0) <= REST_SIGMAS * noise_std else v0


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
        From the ``loop`` metadata key (``open``/``closed ...``), else True when the
        runs carry the excitation ``u_exc``; None when unknown.
    units : SignalUnits
        Units of the signals, from the log's ``unit_*`` metadata.
    min_delay_s : float
        The earliest a command may act relative to its logged instant [s]: 0, or
        ``-command_lead_s`` where the transport sends the command ahead of its
        sample's query (the drive's action delay is identified from there on).
    drive_rates : tuple of (int, DriveRate)
        Per run of a stamped log with the host's instants, the drive clock's rate against the
        host's (:mod:`~servobench.bench.identify.drive_rate`); the stamps of the runs whose
        drift is significant were taken onto the host's seconds. Empty otherwise.
    delay_held_s : float or None
        The action delay [s] the drive's located tick grid fixes: the reads moved onto it, one
        request carrying command and sample, each command acts a whole number of its ticks
        after its sample (:mod:`~servobench.bench.identify.drive_grid`). The joint estimator
        holds the delay there; None: it identifies the delay.
    """

    segments: tuple[Segment, ...]
    fs_hz: float
    design: ExcitationDesign | None = None
    source: str = ""
    notes: tuple[str, ...] = ()
    closed_loop: bool | None = None
    units: SignalUnits = SignalUnits()
    min_delay_s: float = 0.0
    drive_rates: tuple[tuple[int, DriveRate], ...] = ()
    delay_held_s: float | None = None

    @property
    def drive_drift_ppm(self) -> tuple[float, float]:
        """The drive clock's drift against the host's [ppm] and its 1 sigma, weighted over the
        runs (NaN, NaN: none was read)."""
        if not self.drive_rates:
            return math.nan, math.nan
        w = np.array([1.0 / max(r.drift_std_ppm, 1e-9) ** 2 for _, r in self.drive_rates])
        d = np.array([r.drift_ppm for _, r in self.drive_rates])
        return float(w @ d / w.sum()), float(1.0 / math.sqrt(w.sum()))

    @property
    def time_base_error_ppm(self) -> float:
        """How far the log's time base may be off the host's seconds [ppm, 1 sigma], worst run:
        a mapped run's rate sigma; a run left on the drive's seconds (its drift not significant),
        its drift and sigma together. 0 where no rate was read (host instants, or none logged)."""
        worst = 0.0
        for _, r in self.drive_rates:
            worst = max(worst, r.drift_std_ppm if r.significant else math.hypot(r.drift_ppm, r.drift_std_ppm))
        return worst

    @property
    def dt_s(self) -> float:
        return 1.0 / self.fs_hz

    @property
    def derived(self) -> bool:
        return any(s.derived for s in self.segments)

    @property
    def jittered(self) -> bool:
        return any(s.dt_s is not None for s in self.segments)

    @property
    def timing_uncertain(self) -> bool:
        """True when some sample instant is known only within an interval (``t_unc``)."""
        return any(s.t_unc is not None for s in self.segments)

    def switch_pairs(self) -> int:
        """Sample pairs that hold a command change without a reversal (a pair's two velocities
        of one sign): the only pairs in which the drive's delay shows. Fewer than
        :data:`MIN_SWITCH_PAIRS`: every change reverses the axis within its interval, and the
        delay shows in the simulation only."""
        held = 0
        for s in self.segments:
            v, u = np.asarray(s.v), np.asarray(s.u)
            change = np.concatenate(([False], u[1:-1] != u[:-2]))  # u[k] differs from u[k - 1]
            same = ((v[:-1] > 0) & (v[1:] > 0)) | ((v[:-1] < 0) & (v[1:] < 0))
            held += int(np.count_nonzero(change & same))
        return held

    @property
    def has_excitation(self) -> bool:
        """True when every run carries its excitation ``u_exc`` (a closed-loop log)."""
        return all(s.u_exc is not None for s in self.segments)

    def cat(self, name: str) -> np.ndarray:
        """Attribute ``name`` (``"u"``, ``"v"``, ``"v_f"``, ``"position"`` ...) of every run, concatenated."""
        return np.concatenate([getattr(s, name) for s in self.segments])

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
    min_samples: int = MIN_SAMPLES,
) -> Dataset:
    """Build a :class:`Dataset` from a log.

    Parameters
    ----------
    log : ExperimentLog
    velocity_cutoff_hz : float, optional
        Cut-off of the position filter when velocity must be derived [Hz].
    derivative_method : {"butter", "savgol"}
    min_samples : int
        Fewest samples a run must have.

    Raises
    ------
    IdentificationError
        A run is too short, nothing moves, or ``u`` is zero throughout.
    """
    fs = float(log.fs_hz)
    notes: list[str] = []
    if not log.complete:
        notes.append(
            "the log is incomplete (no 'status = complete' trailer): the run was cut short"
        )
    segments = []
    rates: list[tuple[int, DriveRate]] = []
    stamped = log.metadata.get("clock_source", "").strip() == "drive"
    for r in log.runs:
        if len(r) < min_samples:
            raise IdentificationError(
                f"run {r.run} has {len(r)} samples; at least {min_samples} are needed"
            )
        rate = drive_rate(r.t, r.extra["t_host"]) if stamped and "t_host" in r.extra else None
        mapped = rate is not None and rate.significant
        if rate is not None and rate.is_clock:
            rates.append((r.run, rate))
        if mapped:
            acted = r.extra.get(ACT_COLUMN)
            extra = r.extra if acted is None else {**r.extra, ACT_COLUMN: onto_host_seconds(acted, rate)}
            r = replace(r, t=onto_host_seconds(r.t, rate), extra=extra)
        segment, how = _segment(r, fs, velocity_cutoff_hz, derivative_method, per_interval=mapped)
        segments.append(segment)
        notes.extend(note for note in how if note not in notes)
    if not any(_moves(s) for s in segments):
        raise IdentificationError(
            "no motion in the data: the axis does not move (velocity and position never change)"
        )
    if not any(np.any(s.u != 0) for s in segments):
        raise IdentificationError("no excitation: the command u is zero throughout the log")
    design = design_from_metadata(log.metadata, fs, log.source)
    shortest = min(len(s) for s in segments)
    if design is not None and shortest < 2 * design.samples_per_period:
        notes.append("fewer than two excitation periods per run: periodic processing disabled")
        design = None
    elif design is not None and shortest // design.samples_per_period != design.periods:
        design = design.with_periods(shortest // design.samples_per_period)
    loop = log.metadata.get("loop", "").strip().lower()
    closed = True if loop.startswith("closed") else False if loop.startswith("open") else None
    if closed is None and all(r.u_exc is not None for r in log.runs):
        closed = True
    if any(r.significant for _, r in rates):
        drifts = ", ".join(f"run {run} {r.drift_ppm:+.1f} +- {r.drift_std_ppm:.1f} ppm" for run, r in rates)
        notes.append(f"the drive's clock drifted against the host's ({drifts}; its time stamps against "
                     "the host's instants): the stamps were taken onto the host's seconds")  # fmt: skip
    lead_s = _lead(log.metadata.get("command_lead_s"))
    if lead_s > 0 and not any(s.derived for s in segments):
        notes.append(f"each command was sent {lead_s * 1e3:.3g} ms ahead of its sample's query "
                     "(command_lead_s): the drive's action delay was identified from -command_lead_s on")  # fmt: skip
    return Dataset(tuple(segments), fs, design, log.source, tuple(notes), closed, log.units, -lead_s,
                   tuple(rates))  # fmt: skip


def _lead(text: str | None) -> float:
    try:
        value = float(text) if text else 0.0
    except ValueError:
        return 0.0
    return value if value > 0 and value == value else 0.0


def _segment(
    r: RunData, fs_hz: float, cutoff_hz: float | None, method: str, per_interval: bool = False
) -> tuple[Segment, list[str]]:
    """One run as a :class:`Segment`, and notes on how it was prepared (none if plainly).

    ``per_interval``: use the intervals of ``t`` even where they are regular (stamps taken onto
    the host's seconds: the nominal ``1/fs`` is the drive's)."""
    notes = []
    r, repeated = merge_repeated(r)
    if repeated:
        notes.append(
            f"{repeated} repeated samples (a drive tick read twice: the same time stamp) kept once, "
            "with the last command sent in that tick"
        )
    if r.extra.get("t_unc") is not None:
        r, unchanged = merge_unchanged(r)
        if unchanged:
            notes.append(
                f"{unchanged} reads returned the sample before unchanged while the axis moved (a drive "
                "that refreshes its feedback on a tick slower than the host's reads): each kept once, "
                "with the last command sent before the next fresh sample"
            )
    t = np.asarray(r.t, dtype=float)
    dt = np.diff(t)
    nominal = 1.0 / fs_hz
    dt_s = None
    if dt.std() > JITTER_RTOL * dt.mean() or abs(np.median(dt) - nominal) > 1e-2 * nominal:
        dt_s = dt
        notes.append("irregular time stamps: per-sample intervals from t are used")
    elif per_interval:
        dt_s = dt
    motion = None
    if r.v is not None:
        v = np.asarray(r.v, dtype=float)
    else:
        motion = differentiate_position(
            r.x, fs_hz, cutoff_hz, method, t=None if dt_s is None else t
        )
        v = motion.v
        notes.append(
            f"velocity derived from position ({method}, zero-phase, "
            f"cut-off {motion.cutoff_hz:.4g} Hz)"
        )
    x, u_exc, x_ref = (None if a is None else np.asarray(a, dtype=float) for a in (r.x, r.u_exc, r.x_ref))
    u = np.asarray(r.u, dtype=float)
    t_unc = r.extra.get("t_unc")
    if t_unc is not None:
        t_unc = np.asarray(t_unc, dtype=float)
        t_unc = t_unc if np.any(t_unc > 0) else None
    offsets = _act_offsets(r, t)
    if offsets is not None:
        early = int(np.count_nonzero(offsets < 0))
        notes.append(f"{early} commands took force before their row's sample (a later tick's sample "
                     "read: the host woke late; the log's t_act): each acts from where the drive said")  # fmt: skip
    return Segment(r.run, t, u, v, fs_hz, dt_s, motion, x, u_exc, x_ref, t_unc, offsets), notes


def _act_offsets(r: RunData, t: np.ndarray) -> np.ndarray | None:
    """Each row's command's shift [s] from its row's instant to where the drive said it took force
    (the log's ``t_act``); None where the log has none or every command acted at its row's instant."""
    acted = r.extra.get(ACT_COLUMN)
    if acted is None:
        return None
    offsets = np.asarray(acted, dtype=float) - t
    offsets = np.where(np.isfinite(offsets), np.minimum(offsets, 0.0), 0.0)
    return offsets if np.any(offsets < -ACT_TOLERANCE * np.median(np.diff(t))) else None


def merge_repeated(r: RunData) -> tuple[RunData, int]:
    """A run with each repeated sample kept once, and how many rows were merged.

    A drive that stamps its samples with its control tick returns the same
    sample, with the same stamp, to every read inside one tick. Such rows are
    one sample: the first row's feedback and instant stay; its command becomes
    the last one sent before the next distinct sample (a drive acts on the
    last command that arrived before its tick, so the earlier ones in the
    group never acted). The log itself keeps every row.
    """
    t = np.asarray(r.t, dtype=float)
    if t.size < 2:
        return r, 0
    same = np.diff(t) == 0
    if not same.any():
        return r, 0
    keep = np.concatenate(([True], ~same))
    first = np.flatnonzero(keep)
    last = np.concatenate((first[1:] - 1, [t.size - 1]))  # each group's last row
    return _pick_rows(r, first, last), int(t.size - first.size)


def merge_unchanged(r: RunData) -> tuple[RunData, int]:
    """A run without drive time stamps with each stale read kept once, and how many were merged.

    A read whose velocity and position are bit-identical to the previous
    read's, while the axis moves far enough over the interval to have changed
    the position by at least two of its smallest steps, is the same drive
    sample read again (its feedback registers refresh on the drive's tick):
    it is merged into the first read of that sample as :func:`merge_repeated`
    merges equal stamps. Logs without position are returned as they are (a
    noise-free velocity can repeat in a steady state).
    """
    if r.v is None or r.x is None or len(r) < 3:
        return r, 0
    v, x, t = np.asarray(r.v, float), np.asarray(r.x, float), np.asarray(r.t, float)
    dx = np.abs(np.diff(x))
    steps = dx[dx > 0]
    if steps.size == 0:
        return r, 0
    step = float(steps.min())
    stale = (v[1:] == v[:-1]) & (x[1:] == x[:-1]) & (v[1:] != 0) & (np.abs(v[1:]) * np.diff(t) >= 2 * step)
    if not stale.any():
        return r, 0
    keep = np.concatenate(([True], ~stale))
    first = np.flatnonzero(keep)
    last = np.concatenate((first[1:] - 1, [t.size - 1]))
    return _pick_rows(r, first, last), int(t.size - first.size)


def _pick_rows(r: RunData, first: np.ndarray, last: np.ndarray) -> RunData:
    """``r`` with the feedback and instants of rows ``first`` and the commands of rows ``last``."""

    def pick(a, rows):
        return None if a is None else np.asarray(a)[rows]

    extra = {k: pick(a, last if k == ACT_COLUMN else first) for k, a in r.extra.items()}
    return replace(
        r, t=np.asarray(r.t)[first], u=pick(r.u, last), v=pick(r.v, first), x=pick(r.x, first),
        u_exc=pick(r.u_exc, last), x_ref=pick(r.x_ref, last), extra=extra,
    )  # fmt: skip


def _moves(s: Segment) -> bool:
    if s.motion is not None:
        x = s.motion.x
        return bool(np.ptp(x) > 0 and np.any(s.v != 0))
    return bool(np.any(s.v != 0) and np.ptp(s.v) > 0)
