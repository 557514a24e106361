"""The drive's control tick read from a log without its time stamps: each sample moved onto it.

A drive that runs its own control tick ``T`` samples at its last tick before
a request arrives and acts from its next one. A host that logs each sample
at its own instant (the exchange's bracket) puts the sample up to a tick
late, and by a different share of a tick whenever its request crosses one
of the drive's ticks: a constant action delay in the model takes the mean,
not the jumps, which cost the fit (98.2-99.4 % at a 1 ms tick, 2 s periods,
where the same drive with stamps fits 100 %).

Where one request carries the command and asks for the sample (Modbus
FC23, a SYNC, an EtherCAT frame: ``command_lead_s`` 0), the action delay the
model identified is the tick (the sample's lag plus the wait for the next
tick). :func:`find_drive_grid` then looks for the phase ``phase_s`` of the
drive's tick grid on the host's clock: each logged instant ``t`` is moved to
the tick ``phase + T floor((t - phase) / T)`` it was sampled at
(:func:`onto_grid`; reads that land on one tick become one sample, with the
last command sent in it, as repeated stamps do), the command then acts one
tick later, and the pair regression's mean squared residual is compared
over the phases. A grid is kept only where it explains the data clearly
better than the constant delay (:data:`MIN_GAIN`); otherwise, and for logs
with stamps, derived velocity or a command lead, nothing changes.

Pure: arrays and datasets in, a dataset out; no transport.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.identify.dataset import Dataset, Segment
from servobench.errors import IdentificationError

#: Phases tried per tick in each window.
PHASES = 24
#: The grid must cut the mean squared pair residual of the constant delay by this factor.
MIN_GAIN = 1.5
#: Instants this close below a tick (share of the tick) count as on it (float rounding).
ON_TICK = 1e-9
#: Nominal control ticks of drives [s] (16 kHz down to 250 Hz): the identified delay is snapped
#: to the nearest within :data:`SNAP_SHARE`; the drive's crystal's drift is fitted on top.
NICE_TICKS_S = (62.5e-6, 125e-6, 250e-6, 500e-6, 1e-3, 2e-3, 4e-3)
SNAP_SHARE = 0.05
#: Phases of the fine scan over the whole log (a 1 ms tick: 8 us apart).
FINE_PHASES = 120
#: Steps each side of the best fine phase in its last refinement.
REFINE_STEPS = 12
#: Windows the phase is read in [s] (a 50 ppm crystal drifts 25 us in one).
WINDOW_S = 0.5
#: Fewest pairs a window needs to read its phase.
MIN_WINDOW_PAIRS = 50


@dataclass(frozen=True)
class DriveGrid:
    """The drive's tick grid on the log's clock: ticks at ``(phase_s + n tick_s) / (1 - drift)``
    [s]: the nominal tick ``tick_s``, the phase ``phase_s`` in ``[0, tick_s)`` at ``t = 0`` and the
    drive clock's drift against the host's (``drift``: a fraction, ppm times 1e-6), and how much
    the grid cut the mean squared pair residual (``gain``, > 1)."""

    tick_s: float
    phase_s: float
    gain: float
    drift: float = 0.0

    def index(self, t_s: np.ndarray) -> np.ndarray:
        """The tick each instant ``t_s`` [s] was sampled at (the last at or before it)."""
        return np.floor(((1.0 - self.drift) * np.asarray(t_s, dtype=float) - self.phase_s) / self.tick_s + ON_TICK)

    def instant(self, n: np.ndarray) -> np.ndarray:
        """The instants [s] of ticks ``n`` on the log's clock."""
        return (self.phase_s + self.tick_s * np.asarray(n, dtype=float)) / (1.0 - self.drift)

    def note(self, merged: int) -> str:
        return (
            f"the drive's control tick ({self.tick_s * 1e3:.4g} ms) located on the host's clock (phase "
            f"{self.phase_s * 1e3:.4g} ms, drift {self.drift * 1e6:.3g} ppm): each sample moved to the tick it "
            f"was taken at, its command acting from the next ({merged} reads of one tick kept once); the "
            f"pair residual fell {self.gain:.3g} times against a constant delay"
        )


def onto_grid(segment: Segment, grid: DriveGrid) -> tuple[Segment, int]:
    """``segment`` with each instant moved to the tick it was sampled at, and the reads merged.

    Reads whose instants fall on one tick are one sample: the first read's
    feedback, the last read's command. The per-interval steps become whole
    ticks; ``t_unc`` stays as logged (the tick a read landed on is known no
    better than the host's bracket).
    """
    t = np.asarray(segment.t, dtype=float)
    k = grid.index(t)
    keep = np.concatenate(([True], np.diff(k) != 0))
    if np.any(np.diff(k) < 0):
        raise IdentificationError("the log's instants go back: no tick grid can hold them")
    first = np.flatnonzero(keep)
    last = np.concatenate((first[1:] - 1, [t.size - 1]))
    t_new = grid.instant(k[first])

    def pick(a, rows):
        return None if a is None else np.asarray(a)[rows]

    moved = replace(
        segment, t=t_new, u=segment.u[last], v=segment.v[first], x=pick(segment.x, first),
        u_exc=pick(segment.u_exc, last), x_ref=pick(segment.x_ref, last),
        t_unc=pick(segment.t_unc, first), dt_s=np.diff(t_new),
    )  # fmt: skip
    return moved, int(t.size - first.size)


def on_grid(data: Dataset, grid: DriveGrid) -> tuple[Dataset, int]:
    """Every run of ``data`` on the grid (:func:`onto_grid`), and the reads merged in all."""
    segments, merged = [], 0
    for s in data.segments:
        moved, n = onto_grid(s, grid)
        segments.append(moved)
        merged += n
    return replace(data, segments=tuple(segments)), merged


def applicable(data: Dataset, delay_s: float) -> bool:
    """A log whose instants are the host's (``t_unc``), with measured velocity, one request per
    exchange (no command lead), and an action delay of at least a fiftieth of a cycle."""
    return (
        data.timing_uncertain
        and not data.derived
        and data.min_delay_s == 0.0
        and delay_s > 0.02 * data.dt_s
    )


def nominal_ticks_s(delay_s: float, delay_std_s: float = 0.0) -> list[float]:
    """The nominal ticks [s] the delay ``delay_s`` [s] (1 sigma ``delay_std_s``) may stand for,
    nearest first: within :data:`SNAP_SHARE`, or three sigma, of it."""
    reach = max(SNAP_SHARE * delay_s, 3.0 * delay_std_s)
    near = [t for t in NICE_TICKS_S if abs(t - delay_s) <= max(reach, SNAP_SHARE * t)]
    return sorted(near, key=lambda t: abs(t - delay_s))


def find_drive_grid(data: Dataset, model, delay_std_s: float = 0.0) -> DriveGrid | None:
    """The best of :func:`find_grid_at` over the nominal ticks the model's delay may stand for
    (:func:`nominal_ticks_s`), or None where none explains the data clearly better."""
    if not applicable(data, model.delay_s):
        return None
    found = [g for t in nominal_ticks_s(model.delay_s, delay_std_s) if (g := find_grid_at(data, model, t))]
    return max(found, key=lambda g: g.gain) if found else None


def find_grid_at(data: Dataset, model, tick: float) -> DriveGrid | None:
    """The drive's tick grid with nominal tick ``tick`` [s] on the host's clock that best explains
    ``data`` under ``model`` (whose ``delay_s`` is about one tick), or None where no grid explains it
    clearly better than the model's constant delay.

    In each
    window of :data:`WINDOW_S` the phase is the one of :data:`PHASES` (refined
    between its neighbours) whose grid leaves the model's pair residual
    smallest, the command acting one tick after its sample; the phases,
    unwrapped along the run, give the grid's phase and the drive clock's drift
    by a straight-line fit (median-robust). The grid is kept where the refitted
    pair regression's mean squared residual falls :data:`MIN_GAIN` times below
    the constant delay's.
    """
    from servobench.bench.identify.joint import pair_residual_ms

    tau = model.time_constant_s
    try:
        baseline = pair_residual_ms(data, model.delay_s, tau)  # the constant delay identified
    except IdentificationError:
        return None
    model = replace(model, delay_s=tick)
    t_end = max(float(s.t[-1]) for s in data.segments)
    edges = np.arange(0.0, t_end + WINDOW_S, WINDOW_S)
    phases = np.arange(PHASES) * tick / PHASES
    costs = np.full((PHASES, edges.size - 1), np.nan)
    counts = np.zeros(edges.size - 1)
    for i, phase in enumerate(phases):
        sums = np.zeros(edges.size - 1)
        n = np.zeros(edges.size - 1)
        for seg in data.segments:
            moved, _ = onto_grid(seg, DriveGrid(tick, phase, 1.0))
            t_pair, e = _model_residuals(moved, model, tick)
            w = np.clip(np.searchsorted(edges, t_pair, side="right") - 1, 0, edges.size - 2)
            sums += np.bincount(w, e * e, edges.size - 1)
            n += np.bincount(w, None, edges.size - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            costs[i] = sums / n
        counts = np.maximum(counts, n)
    usable = (counts >= MIN_WINDOW_PAIRS) & np.all(np.isfinite(costs), axis=0)
    if np.count_nonzero(usable) < 2:
        return None
    centres = 0.5 * (edges[:-1] + edges[1:])[usable]
    read = np.array([_best_phase(costs[:, j], tick) for j in np.flatnonzero(usable)])
    unwrapped = np.unwrap(read * (2 * np.pi / tick)) * (tick / (2 * np.pi))
    slope, _ = _robust_line(centres, unwrapped)
    # phase(t) = phase + slope t: ticks at (phase + n T) / (1 - slope). The windows give the drift;
    # the phase, and whether the drift beats none (a drive on the host's own clock), come from
    # the model's residual over the whole log on a fine scan of phases.
    best_cost, grid = math.inf, None
    for drift in {0.0, float(slope)}:
        for phase in np.arange(FINE_PHASES) * tick / FINE_PHASES:
            trial = DriveGrid(tick, float(phase), 1.0, drift)
            cost = _grid_cost(data, model, trial)
            if cost < best_cost:
                best_cost, grid = cost, trial
    if grid is None:
        return None
    step = tick / FINE_PHASES
    for phase in grid.phase_s + np.linspace(-step, step, 2 * REFINE_STEPS + 1):
        trial = DriveGrid(tick, float(phase % tick), 1.0, grid.drift)
        cost = _grid_cost(data, model, trial)
        if cost < best_cost:
            best_cost, grid = cost, trial
    try:
        moved, _ = on_grid(data, grid)
        best = pair_residual_ms(moved, tick, tau)
    except IdentificationError:
        return None
    if not (best > 0 and baseline / best >= MIN_GAIN):
        return None
    return replace(grid, gain=baseline / best)


def _grid_cost(data: Dataset, model, grid: DriveGrid) -> float:
    """Mean squared residual of ``model`` over every run moved onto ``grid``."""
    total, count = 0.0, 0
    for seg in data.segments:
        moved, _ = onto_grid(seg, grid)
        _, e = _model_residuals(moved, model, grid.tick_s / (1.0 - grid.drift))
        total += float(e @ e)
        count += e.size
    return total / count if count else math.inf


def _model_residuals(seg: Segment, model, tick_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's end instant [s] and its residual under ``model`` with the command acting one
    tick after its sample, over the pairs that keep one velocity sign."""
    from servobench.bench.identify.delay import effective_command

    v, t = seg.v, seg.t
    if v.size < 3:
        return np.zeros(0), np.zeros(0)
    dt = np.diff(t)
    u_eff = effective_command(seg.u, dt, tick_s, model.time_constant_s)
    a = np.exp(-model.B * dt / model.M)
    pos = (v[:-1] > 0) & (v[1:] > 0)
    neg = (v[:-1] < 0) & (v[1:] < 0)
    force = np.where(pos, model.coulomb_pos, 0.0) - np.where(neg, model.coulomb_neg, 0.0)
    e = v[1:] - a * v[:-1] - (1.0 - a) / model.B * (u_eff - force)
    keep = pos | neg
    return t[1:][keep], e[keep]


def _best_phase(cost: np.ndarray, tick_s: float) -> float:
    """The phase of least cost, refined by a parabola through it and its (circular) neighbours."""
    n = cost.size
    i = int(np.argmin(cost))
    c0, c1, c2 = cost[(i - 1) % n], cost[i], cost[(i + 1) % n]
    den = c0 - 2 * c1 + c2
    shift = 0.5 * (c0 - c2) / den if den > 0 else 0.0
    return ((i + float(np.clip(shift, -0.5, 0.5))) * tick_s / n) % tick_s


def _robust_line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """``(slope, intercept)`` of ``y ~ x`` by least squares, refitted once without the points
    further than three median deviations from the first line."""
    slope, intercept = np.polyfit(x, y, 1) if x.size >= 2 else (0.0, float(y[0]))
    r = y - (slope * x + intercept)
    mad = float(np.median(np.abs(r - np.median(r)))) * 1.4826
    keep = np.abs(r) <= 3 * mad + 1e-15
    if 2 <= np.count_nonzero(keep) < x.size:
        slope, intercept = np.polyfit(x[keep], y[keep], 1)
    return float(slope), float(intercept)
