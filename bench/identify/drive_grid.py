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
with stamps or derived velocity, nothing changes.

Where the command goes ahead of its sample's query (ODrive serial:
``command_lead_s`` ``L`` > 0), each row's command acts from the first tick after
``t - L`` and its sample is the tick before ``t``: the action follows the
sample by no tick or by one, row by row, which a constant delay cannot hold.
On the grid each command then carries its own offset
(:attr:`~servobench.bench.identify.dataset.Segment.act_offset_s`) around the
mean delay. At such a link's rates every command switch reverses the axis
within its interval, so no pair of samples holds a switch; the phase is then
read from the model's simulation of each run, not from its pairs.

Pure: arrays and datasets in, a dataset out; no transport.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from servobench.bench.identify.dataset import MIN_SWITCH_PAIRS, Dataset, Segment
from servobench.bench.identify.pair_placement import place_by_pairs
from servobench.errors import IdentificationError

#: Phases tried per tick in each window.
PHASES = 24
#: The grid must cut the mean squared pair residual of the constant delay by this factor.
MIN_GAIN = 1.5
#: Where the simulation judges a grid (:func:`by_simulation`) the constant-delay model it is judged
#: under has had its parameters bent by the misplaced reads (at a slow rate the delay trades against
#: the mass): every nominal tick's grid is identified on (the best :data:`TRIALS` by their gain
#: with a command lead, whose delay bounds the tick from below), and the best kept where it
#: verifies :data:`MIN_GAIN` times better in mean square (:func:`refit_kept`).
TRIAL_GAIN = 0.0
TRIALS = 3
#: Instants this close below a tick (share of the tick) count as on it (float rounding).
ON_TICK = 1e-9
#: Nominal control ticks of drives [s] (16 kHz down to 250 Hz): the identified delay is snapped
#: to the nearest within :data:`SNAP_SHARE` of a tick; the drive's crystal's drift is fitted on top.
#: The reads a tick off bias the constant delay the grid is looked for from: a host whose
#: SYNC kept landing on the drive's tick boundary (CANopen at 1 ms, under load, the drive's
#: record showing 472 of 8028 reads answered from the tick of the read before) gave 1.090 +- 0.029 ms for
#: a tick of 1 ms, a fit of 96.7 % and M 0.12 % off, beyond a snap of 5 %. Nominal ticks are
#: a factor of two apart, so a quarter of a tick never reaches two of them.
NICE_TICKS_S = (62.5e-6, 125e-6, 250e-6, 500e-6, 1e-3, 2e-3, 4e-3)
SNAP_SHARE = 0.25
#: Phases of the fine scan over the whole log (a 1 ms tick: 8 us apart).
FINE_PHASES = 120
#: Steps each side of the best fine phase in its last refinement.
REFINE_STEPS = 12
#: Windows the phase is read in [s] (a 50 ppm crystal drifts 25 us in one); longer where the
#: log's rate gives them fewer than :data:`MIN_WINDOW_PAIRS` samples.
WINDOW_S = 0.5
#: Fewest pairs a window needs to read its phase.
MIN_WINDOW_PAIRS = 50


@dataclass(frozen=True)
class DriveGrid:
    """The drive's tick grid on the log's clock: ticks at ``(phase_s + n tick_s) / (1 - drift)``
    [s]: the nominal tick ``tick_s``, the phase ``phase_s`` in ``[0, tick_s)`` at ``t = 0`` and the
    drive clock's drift against the host's (``drift``: a fraction, ppm times 1e-6), and how much
    the grid cut the mean squared residual (``gain``, > 1); ``lead_s`` [s]: how long before its
    sample's query each command was sent (0: one request carries both)."""

    tick_s: float
    phase_s: float
    gain: float
    drift: float = 0.0
    lead_s: float = 0.0
    simulated: bool = False

    def index(self, t_s: np.ndarray) -> np.ndarray:
        """The tick each instant ``t_s`` [s] was sampled at (the last at or before it)."""
        return np.floor(((1.0 - self.drift) * np.asarray(t_s, dtype=float) - self.phase_s) / self.tick_s + ON_TICK)

    def action_index(self, t_s: np.ndarray) -> np.ndarray:
        """The tick each row's command acts from: the first after its arrival, ``lead_s`` before
        the row's instant ``t_s`` [s] (the tick after the sample where one request carries both)."""
        return self.index(np.asarray(t_s, dtype=float) - self.lead_s) + 1.0

    @property
    def period_s(self) -> float:
        """The tick on the log's clock [s] (the drift taken in)."""
        return self.tick_s / (1.0 - self.drift)

    def instant(self, n: np.ndarray) -> np.ndarray:
        """The instants [s] of ticks ``n`` on the log's clock."""
        return (self.phase_s + self.tick_s * np.asarray(n, dtype=float)) / (1.0 - self.drift)

    def note(self, merged: int) -> str:
        return (
            f"the drive's control tick ({self.tick_s * 1e3:.4g} ms) located on the host's clock (phase "
            f"{self.phase_s * 1e3:.4g} ms, drift {self.drift * 1e6:.3g} ppm): each sample moved to the tick it "
            f"was taken at, its command acting from {self._acting()} ({merged} reads of one tick kept "
            f"once); the {'simulation' if self.simulated else 'pair'} residual fell {self.gain:.3g} times "
            "against a constant delay"
        )

    def _acting(self) -> str:
        if self.lead_s > 0:
            return f"the first tick after its arrival, {self.lead_s * 1e3:.3g} ms before the query"
        return "the next"


@dataclass(frozen=True)
class RunGrids:
    """The drive's tick grid located in each run: every run's clock starts at its own first
    sample, so each has its own phase (and drift) on one nominal tick. ``gain``: how much the
    grids cut the mean squared residual over the whole log against a constant delay."""

    grids: tuple[tuple[int, DriveGrid], ...]
    gain: float

    @property
    def tick_s(self) -> float:
        return self.grids[0][1].tick_s

    @property
    def lead_s(self) -> float:
        return self.grids[0][1].lead_s

    def for_run(self, run: int) -> DriveGrid:
        """The grid of run ``run``."""
        for number, grid in self.grids:
            if number == run:
                return grid
        raise IdentificationError(f"no tick grid was located for run {run}")

    def note(self, merged: int) -> str:
        phases = ", ".join(f"run {r} {g.phase_s * 1e3:.4g} ms" for r, g in self.grids)
        drift = max((g.drift for _, g in self.grids), key=abs)
        return replace(self.grids[0][1], gain=self.gain, drift=drift).note(merged).replace(
            f"phase {self.grids[0][1].phase_s * 1e3:.4g} ms", f"phase {phases}")


def _grid_of(grid: DriveGrid | RunGrids, run: int) -> DriveGrid:
    return grid.for_run(run) if isinstance(grid, RunGrids) else grid


def onto_grid(
    segment: Segment, grid: DriveGrid, mean_delay_s: float | None = None, placed: Placement | None = None
) -> tuple[Segment, int]:
    """``segment`` with each instant moved to the tick it was sampled at, and the reads merged.

    Reads whose instants fall on one tick are one sample: the first read's
    feedback, the last read's command. The per-interval steps become whole
    ticks; ``t_unc`` stays as logged (the tick a read landed on is known no
    better than the host's bracket). With a command lead (``grid.lead_s``)
    each command's action tick is its own (:meth:`DriveGrid.action_index`):
    its offset from ``mean_delay_s`` [s] (the mean over every run,
    :func:`grid_delay_s`; this run's own when None) is kept as ``act_offset_s``.
    ``placed``: each read's ticks where already decided (:func:`place_reads`).
    """
    t = np.asarray(segment.t, dtype=float)
    placed = place_reads(segment, grid) if placed is None else placed
    k = placed.sample
    if np.any(np.diff(k) < 0):
        raise IdentificationError("the log's instants go back: no tick grid can hold them")
    first, last = _merged_rows(k)
    t_new = grid.instant(k[first])

    def pick(a, rows):
        return None if a is None else np.asarray(a)[rows]

    offsets = None
    if grid.lead_s > 0:
        delays = (placed.action[last] - k[first]) * grid.period_s
        offsets = delays - (float(np.mean(delays)) if mean_delay_s is None else mean_delay_s)
    moved = replace(
        segment, t=t_new, u=segment.u[last], v=segment.v[first], x=pick(segment.x, first),
        u_exc=pick(segment.u_exc, last), x_ref=pick(segment.x_ref, last),
        t_unc=pick(segment.t_unc, first), dt_s=np.diff(t_new), act_offset_s=offsets,
    )  # fmt: skip
    return moved, int(t.size - first.size)


def _merged_rows(k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first and the last read of each run of equal ticks ``k`` (the reads one sample merges)."""
    first = np.flatnonzero(np.concatenate(([True], np.diff(k) != 0)))
    return first, np.concatenate((first[1:] - 1, [k.size - 1]))


@dataclass(frozen=True)
class Placement:
    """Where each read of a run went on its grid: the tick its sample was taken at (``sample``)
    and the tick its command acts from (``action``), as tick indices, shape ``(n,)``."""

    sample: np.ndarray
    action: np.ndarray


#: A command whose arrival (``t - lead_s``) lies this share of a tick (or its read's ``t_unc``, if
#: more) from a tick may act from either: the simulation decides (the lead itself is the wire's).
ACTION_DOUBT = 0.15


def place_reads(segment: Segment, grid: DriveGrid, model=None, pairs: bool = False,
                rng: np.random.Generator | None = None) -> Placement:  # fmt: skip
    """Each read's sample and action tick on ``grid`` (:class:`Placement`); with ``model``, and a
    command lead, a read whose instants are in doubt decided by ``model``'s simulation (with
    ``rng``, one draw by its odds under the model, :func:`_drawn`); without a lead, and
    ``pairs``, by ``model``'s one-step pairs around it
    (:func:`~servobench.bench.identify.pair_placement.place_by_pairs`: a read and its command
    move together; with ``rng``, one draw from the pairs' posterior instead of its mode).

    The command of a read arrived ``lead_s`` before it and acts from the first
    tick after; where a tick lies within the doubt of that arrival
    (:data:`ACTION_DOUBT`) and the command changes there, the action tick that
    simulates the samples up to the next change better is kept (one change at a
    time, in order). Then the sample: with the actions fixed, a read whose
    bracket ``t +- t_unc`` holds a tick takes the tick before it or after it,
    whichever's simulated velocity lies nearer its own (the simulation does not
    depend on the samples). Without a lead, a model or ``t_unc``, the ticks are
    :meth:`DriveGrid.index`'s and :meth:`DriveGrid.action_index`'s.
    """
    t = np.asarray(segment.t, dtype=float)
    k, ka = grid.index(t), grid.action_index(t)
    if model is None or segment.t_unc is None or t.size < 2:
        return Placement(k, ka)
    if grid.lead_s <= 0:
        if not pairs:
            return Placement(k, ka)
        k = place_by_pairs(t, segment.t_unc, segment.u, segment.v, k, grid.instant, grid.period_s,
                           model.to_plant_params(), rng)  # fmt: skip
        return Placement(k, k + 1.0)
    unc = np.asarray(segment.t_unc, dtype=float)
    v = np.asarray(segment.v, dtype=float)
    ka = _decide_actions(segment, grid, model, k, ka, np.maximum(unc, ACTION_DOUBT * grid.tick_s), rng)
    below = grid.instant(k) >= t - unc  # the query may have come before tick k: sample k - 1
    above = grid.instant(k + 1) <= t + unc  # or after tick k + 1: sample k + 1
    alt = np.where(below, k - 1, np.where(above, k + 1, k))
    doubt = alt != k
    if doubt.any():
        switches = np.maximum.accumulate(grid.instant(ka))
        v_k, v_alt = _velocity_at(grid.instant(k), grid.instant(alt), segment.u, switches, model, float(v[0]))
        if rng is not None:
            take = _drawn(doubt, v, v_k, v_alt, rng)
        else:
            edge = np.where(below, t - grid.instant(k), grid.instant(k + 1) - t)  # to the tick crossed
            take = _share_undecided(doubt & (np.abs(v_alt - v) < np.abs(v_k - v)), doubt, below, v, v_k, v_alt,
                                    edge)  # fmt: skip
        k = np.maximum.accumulate(np.where(take, alt, k))
    return Placement(k, ka)


def _drawn(doubt: np.ndarray, v: np.ndarray, v_k: np.ndarray, v_alt: np.ndarray,
           rng: np.random.Generator) -> np.ndarray:  # fmt: skip
    """One draw of which reads in doubt take their other tick, each by its odds under the model:
    its two ticks' simulated velocities against the read, the residuals normal with the model's
    robust residual scale on the reads not in doubt. A read the simulation decides keeps its
    side; one whose two ticks look alike (a settled stretch) goes either way at even odds.
    Placed by the grid alone, each read anywhere in its bracket, served ODrive serial logs (a
    command sent ahead of its query, seven at ticks of 0.25-2 ms) predicted 0.87-10.7 % at two
    sigma for models 0.00004-0.18 % off."""
    scale = _read_scale(doubt, v, v_k, v_alt)
    other = _other_side((v_alt - v) ** 2 - (v_k - v) ** 2, scale)
    return doubt & (rng.random(v.size) < other)


#: Fewest reads not in doubt whose residual gives the model's scale (:func:`_read_scale`).
MIN_CLEAR_READS = 20


def _read_scale(doubt: np.ndarray, v: np.ndarray, v_k: np.ndarray, v_alt: np.ndarray) -> float:
    """The model's robust residual scale on the reads: on those not in doubt; where fewer than
    :data:`MIN_CLEAR_READS` are (brackets as wide as the tick put nearly every read in doubt),
    on every read at the nearer of its two ticks.

    A scale of none decides every read in doubt by the last digits of its two ticks' velocities:
    a served ODrive serial log at a 0.25 ms tick (brackets +-0.16 ms, every read in doubt), placed
    under the constant-delay model, moved 11 of a run's 21 command changes' settled reads a tick
    early where the true model moves one, and the delay came out 0.081 ms off the record.
    """
    clear = ~doubt
    if np.count_nonzero(clear) >= MIN_CLEAR_READS:
        return _robust_scale((v_k - v)[clear], v)
    nearer = np.where(doubt, np.minimum(np.abs(v_k - v), np.abs(v_alt - v)), np.abs(v_k - v))
    return _robust_scale(nearer, v)


def _robust_scale(residual: np.ndarray, v: np.ndarray) -> float:
    """The residuals' robust scale (the normal-consistent median of their size), at least a
    rounding of the velocity ``v``'s largest value (residuals that are all zero)."""
    scale = 1.4826 * float(np.median(np.abs(residual))) if residual.size else 0.0
    return max(scale, 1e-12 * float(np.max(np.abs(v), initial=1.0)))


def _other_side(cost_gap, scale: float):
    """The probability that the other side is right, from the gap of its squared residuals over
    the side's own (``cost_gap``), the residuals normal of ``scale``."""
    z = np.clip(np.asarray(cost_gap, dtype=float) / (2.0 * scale * scale), -700.0, 700.0)
    return 1.0 / (1.0 + np.exp(z))


#: A read in doubt is decided by the simulation where its two candidate ticks' velocities differ
#: by more than this many times the model's robust residual scale on the reads not in doubt.
DECISIVE = 3.0


def _share_undecided(take: np.ndarray, doubt: np.ndarray, below: np.ndarray, v: np.ndarray,
                     v_k: np.ndarray, v_alt: np.ndarray, edge: np.ndarray) -> np.ndarray:  # fmt: skip
    """``take`` (a read in doubt takes its other tick), with the reads the simulation cannot
    decide set in the share the decided ones of their side showed.

    On a steady stretch (a command held until the axis settled: every command change's own
    read) the two ticks' velocities are alike, and the choice is the noise's; but the host's
    bracket is off the drive's read alike for every read of a run (a port's latency), so the
    decided reads (in the transients) show on which side the reads fall, and how often. The
    undecided reads of a side that cross take its share nearest the tick they cross first
    (``edge`` [s]: from each read's instant to that tick): a port's latency moves those first.
    Spread evenly along the run instead, 19 served ODrive serial logs at a 0.25 ms tick put
    their delay 0.002-0.027 ms later than the drive's record, where this puts it 0.002-0.021 ms.
    Without decided reads on a side, its undecided reads keep the bracket's middle.
    """
    scale = _read_scale(doubt, v, v_k, v_alt)
    decided = doubt & (np.abs(v_alt - v_k) > DECISIVE * scale)
    out = take.copy()
    for side in (below, ~below):
        known, rows = decided & side, np.flatnonzero(doubt & side & ~decided)
        out[rows] = False
        count = int(round(float(np.mean(take[known])) * rows.size)) if known.any() else 0
        if count:
            out[rows[np.argsort(edge[rows], kind="stable")[:count]]] = True
    return out


def _decide_actions(segment: Segment, grid: DriveGrid, model, k: np.ndarray, ka: np.ndarray,
                    unc: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:  # fmt: skip
    """The action ticks ``ka`` with each command change whose arrival is in doubt (within ``unc``
    [s] of a tick) moved to the side that simulates the samples up to the next change better;
    with ``rng``, to a side drawn by the two sides' odds under the model (normal residuals of
    the model's robust scale on the whole run)."""
    arrival = np.asarray(segment.t, dtype=float) - grid.lead_s
    early = grid.instant(ka - 1) > arrival - unc  # it may have come before tick ka - 1
    late = grid.instant(ka) <= arrival + unc  # or after tick ka
    alt = np.where(early, ka - 1, np.where(late, ka + 1, ka))
    u, v = np.asarray(segment.u, dtype=float), np.asarray(segment.v, dtype=float)
    changes = np.flatnonzero(np.concatenate(([True], u[1:] != u[:-1])))
    doubtful = [int(r) for r in changes if alt[r] != ka[r]]
    if not doubtful:
        return ka
    ka = ka.copy()
    at = grid.instant(k)
    if rng is not None:
        sim, _ = _velocity_at(at, at, u, np.maximum.accumulate(grid.instant(ka)), model, float(v[0]))
        scale = _robust_scale(sim - v, v)
    for r in doubtful:
        after = changes[changes > r]
        window = slice(r, int(after[0]) + 1 if after.size else v.size)
        costs = []
        for cand in (ka[r], alt[r]):
            trial = ka.copy()
            trial[r] = cand
            sim, _ = _velocity_at(at, at, u, np.maximum.accumulate(grid.instant(trial)), model, float(v[0]))
            costs.append(float(np.sum((sim[window] - v[window]) ** 2)))
        if rng is not None:
            if rng.random() < _other_side(costs[1] - costs[0], scale):
                ka[r] = alt[r]
        elif costs[1] < costs[0]:
            ka[r] = alt[r]
    # A command that repeats the one before acts alike on either tick: for the mean delay, the
    # rows in doubt among them take the other tick in the share the changes showed.
    share = np.mean([ka[r] == alt[r] for r in doubtful])
    still = np.setdiff1d(np.flatnonzero(alt != ka), doubtful)
    count = int(round(share * still.size))
    if count:
        pick = still[np.unique(np.round(np.linspace(0, still.size - 1, count)).astype(int))]
        ka[pick] = alt[pick]
    return ka


def _velocity_at(
    at_a: np.ndarray, at_b: np.ndarray, u: np.ndarray, switches: np.ndarray, model, v0: float
) -> tuple[np.ndarray, np.ndarray]:
    """``model``'s velocity at the instants ``at_a`` and ``at_b`` [s], command ``u[j]`` in force from
    ``switches[j]`` [s] (0 before the first), from ``v0`` at the earliest instant."""
    from servobench.bench.identify.simulation import simulate_variable_dt

    start = min(float(at_a[0]), float(at_b[0]))
    inside = switches[(switches > start) & (switches < max(float(at_a[-1]), float(at_b[-1])))]
    instants = np.unique(np.concatenate(([start], at_a, at_b, inside)))
    j = np.searchsorted(switches, instants + 1e-12 * grid_scale(instants), side="right") - 1
    u_m = np.where(j >= 0, np.asarray(u, dtype=float)[np.clip(j, 0, None)], 0.0)
    v = simulate_variable_dt(u_m, np.diff(instants), model.to_plant_params(), v0)
    return v[np.searchsorted(instants, at_a)], v[np.searchsorted(instants, at_b)]


def grid_scale(instants: np.ndarray) -> float:
    """A time scale [s] for rounding tolerances on ``instants``: their mean step."""
    return float((instants[-1] - instants[0]) / max(instants.size - 1, 1)) if instants.size > 1 else 1.0


def grid_delay_s(data: Dataset, grid: DriveGrid | RunGrids, placed: dict | None = None) -> float:
    """The mean action delay [s] on ``grid`` over every run: one tick without a command lead; with
    one, the mean over the samples whose command changed of ticks from the sample to its
    command's action (each run's :class:`Placement` from ``placed``, keyed by run, where given).

    Only a change shows its delay in the motion: a command that repeats the one before acts
    alike from either tick, so the log cannot tell the repeats' delays, and a mean over them
    would be the placement's guess (the drive's record counts the same: its
    ``mean_change_delay_s``). Every row's offset is taken from this mean.
    """
    if grid.lead_s <= 0:
        return _grid_of(grid, data.segments[0].run).period_s
    total, count = 0.0, 0
    for s in data.segments:
        g = _grid_of(grid, s.run)
        p = place_reads(s, g) if not placed or placed.get(s.run) is None else placed[s.run]
        k = p.sample
        first, last = _merged_rows(k)
        u = np.asarray(s.u, dtype=float)[last]
        change = np.concatenate(([True], u[1:] != u[:-1]))
        total += float(np.sum(p.action[last][change] - k[first][change])) * g.period_s
        count += int(np.count_nonzero(change))
    return total / count if count else _grid_of(grid, data.segments[0].run).period_s


def on_grid(data: Dataset, grid: DriveGrid | RunGrids, model=None, pairs: bool = False,
            rng: np.random.Generator | None = None) -> tuple[Dataset, int]:  # fmt: skip
    """Every run of ``data`` on the grid (:func:`onto_grid`; its own where ``grid`` holds one per
    run), and the reads merged in all; with ``model`` and a command lead (or ``pairs``), the
    reads near a tick placed by it (:func:`place_reads`; ``rng``: drawn from the pairs' posterior)."""
    segments, merged = [], 0
    placed = {s.run: place_reads(s, _grid_of(grid, s.run), model, pairs, rng) for s in data.segments}
    mean_delay = grid_delay_s(data, grid, placed) if grid.lead_s > 0 else None
    for s in data.segments:
        moved, n = onto_grid(s, _grid_of(grid, s.run), mean_delay, placed[s.run])
        segments.append(moved)
        merged += n
    return replace(data, segments=tuple(segments)), merged


def applicable(data: Dataset, delay_s: float) -> bool:
    """A log whose instants are the host's (``t_unc``), with measured velocity, and an action
    delay of at least a fiftieth of a cycle, or a command lead (whose rows' delays may average
    to anything down to minus the lead), or one whose delay was read from a simulation that
    trades it against the mass (:func:`by_simulation`)."""
    if not data.timing_uncertain or data.derived:
        return False
    return data.min_delay_s < 0.0 or delay_s > 0.02 * data.dt_s or by_simulation(data)


def nominal_ticks_s(
    delay_s: float, delay_std_s: float = 0.0, lead_s: float = 0.0, longest_s: float = math.inf
) -> list[float]:
    """The nominal ticks [s] the delay ``delay_s`` [s] (1 sigma ``delay_std_s``) may stand for,
    nearest first: within :data:`SNAP_SHARE`, or three sigma, of it.

    A command sent ``lead_s`` [s] ahead of its query acts a tick after its sample, or in the
    sample's own tick where a tick fell within the lead; as the host's cycle keeps its phase
    against the drive's ticks, any share of the rows may do either, and the mean delay is
    anywhere up to a tick: then every nominal tick from the delay on, up to ``longest_s``, and the
    one below (the constant delay identified where the rows' delays differ is biased: a served
    serial log at a 2 ms tick gave 2.40 +- 0.13 ms).
    """
    reach = max(SNAP_SHARE * abs(delay_s), 3.0 * delay_std_s)
    if lead_s > 0:  # (a tick shorter than the lead may even put the action before the sample)
        near = [t for t in NICE_TICKS_S if abs(delay_s) - max(reach, SNAP_SHARE * t) <= t <= longest_s]
        below = [t for t in NICE_TICKS_S if t < min(near, default=math.inf)]
        near = ([below[-1]] if below and below[-1] <= longest_s else []) + near
    else:
        near = [t for t in NICE_TICKS_S if abs(t - delay_s) <= max(reach, SNAP_SHARE * t)]
    return sorted(near, key=lambda t: abs(t - delay_s))


#: Where the simulation judges a grid (:func:`by_simulation`), the model identified on it must act
#: within this many of its delay's sigma, or this share of a tick, of a whole number of ticks after
#: the sample (:func:`acts_on_grid`).
GRID_DELAY_SIGMAS = 2.5
GRID_DELAY_SHARE = 0.25


def acts_on_grid(grid: DriveGrid | RunGrids, delay_s: float, delay_std_s: float) -> bool:
    """Whether the model identified on ``grid`` acts where the grid says its commands act: a whole
    number of ticks (one at least) after the sample, within :data:`GRID_DELAY_SIGMAS` of the delay's
    1 sigma ``delay_std_s`` [s] or :data:`GRID_DELAY_SHARE` of a tick (reads placed by the grid
    alone, before the pairs place them, bias the delay by about a tenth of a tick). One request
    carrying command and sample, the samples moved onto the drive's ticks leave the model nothing
    but that to find; a grid whose model acts elsewhere explains the log by its freedom, not by the
    drive's clock. At a slow link's rate a grid of twice the tick can verify as well as the tick's
    own: served Modbus RTU at 50 Hz on a 0.25 ms tick, the 0.5 ms grid verified 99.869 % against
    99.859 % with its model acting 0.265 +- 0.077 ms after the sample, and gave the delay 0.340 ms
    (0.09 ms off); on the 0.25 ms grids of eight such logs the delay lay 0.003-0.116 ms from the
    tick (within 1.5 of its sigma), on their 0.5 ms grids 0.125-0.25 ms short of it. True with a
    command lead (each row's command then acts from a tick of its own)."""
    if grid.lead_s > 0 or not math.isfinite(delay_std_s):
        return True
    reach = max(GRID_DELAY_SIGMAS * delay_std_s, GRID_DELAY_SHARE * grid.tick_s)
    return off_grid_s(delay_s, grid.tick_s) <= reach


def off_grid_s(delay_s: float, tick_s: float) -> float:
    """How far the delay ``delay_s`` [s] lies from a whole number of ticks ``tick_s`` [s], one at
    least [s]: the model identified on reads moved onto a located grid, one request carrying
    command and sample, must act there (:func:`acts_on_grid`).
    Where it does not, some reads sit on the wrong tick, and a delay between two whole ticks is
    uncertain by at least its distance to the nearer one: neither the fit's sigma nor the draws
    (which place the reads as the log's model did) see it. A fresh-clone suite gave served Modbus
    RTU at a 0.25 ms tick without stamps, host stalls of 58 ms, 0.413 ms against 0.25 with 0.041 ms
    stated; 0.087 ms from two ticks."""
    ticks = max(1.0, float(round(delay_s / tick_s)))
    return abs(delay_s - ticks * tick_s)


def refit_kept(fit_before_pct: float, fit_after_pct: float) -> bool:
    """A located grid is kept where the model identified on it verifies :data:`MIN_GAIN` times better
    in mean square than the constant delay's (fits [%], ``100 (1 - |e| / |v - mean v|)``)."""
    miss_before, miss_after = 100.0 - fit_before_pct, 100.0 - fit_after_pct
    return miss_after <= 0 or (miss_before / miss_after) ** 2 >= MIN_GAIN


def find_drive_grid(data: Dataset, model, delay_std_s: float = 0.0, min_gain: float = MIN_GAIN) -> RunGrids | None:
    """The best over the nominal ticks the model's delay may stand for (:func:`nominal_ticks_s`)
    of each run's grid (:func:`find_grid_at`), or None where none explains the data clearly
    better (``min_gain``) than the constant delay over the whole log."""
    found = find_drive_grids(data, model, delay_std_s, min_gain)
    return found[0] if found else None


def find_drive_grids(data: Dataset, model, delay_std_s: float = 0.0, min_gain: float = MIN_GAIN) -> list[RunGrids]:
    """Every nominal tick's grids (:func:`find_run_grids`) that cut the constant delay's residual
    ``min_gain`` times under ``model``, best first."""
    if not applicable(data, model.delay_s):
        return []
    lead = max(-data.min_delay_s, 0.0)
    simulated = by_simulation(data)
    # a tick longer than the host's cycle leaves too few distinct ticks to place the reads on,
    # and one shorter than the reads' typical bracket cannot be told from their scatter (twice
    # that left a served serial drive's 0.125 ms tick, brackets of +-0.09 ms, unlocated: fits
    # 99.5 % and M up to 0.3 % off, where the grid gives 99.9 % and 0.1 %)
    ticks = nominal_ticks_s(model.delay_s, delay_std_s, lead, data.dt_s)
    if lead > 0:
        bracket = float(np.median(np.concatenate([s.t_unc for s in data.segments if s.t_unc is not None])))
        ticks = [t for t in ticks if t >= bracket]
    elif simulated:  # the delay was read from a simulation that trades it against the mass: any tick
        # a hundredth of a cycle or more (finer ticks leave no mark at the log's rate)
        ticks = sorted((t for t in NICE_TICKS_S if t >= 0.01 * data.dt_s), key=lambda t: abs(t - model.delay_s))
    found = [g for t in ticks if (g := find_run_grids(data, model, t, lead, min_gain, simulated))]
    return sorted(found, key=lambda g: -g.gain)


def by_simulation(data: Dataset) -> bool:
    """Whether a grid on ``data`` is judged by the model's simulation, not its pairs: with a command
    lead, or where fewer than :data:`MIN_SWITCH_PAIRS` pairs hold a command change (every change
    reverses the axis within its interval, and such intervals are no pairs)."""
    return data.min_delay_s < 0 or data.switch_pairs() < MIN_SWITCH_PAIRS


def find_run_grids(
    data: Dataset, model, tick: float, lead_s: float = 0.0, min_gain: float = MIN_GAIN, simulated: bool = False
) -> RunGrids | None:
    """Each run's grid of nominal tick ``tick`` [s] (:func:`find_grid_at` on that run alone), kept
    where together they cut the whole log's mean squared residual ``min_gain`` times."""
    from servobench.bench.identify.joint import pair_residual_ms

    grids = []
    for seg in data.segments:
        g = find_grid_at(replace(data, segments=(seg,)), model, tick, lead_s, 0.0, simulated or lead_s > 0)
        if g is None:
            return None
        grids.append((seg.run, g))
    found = RunGrids(tuple(grids), 1.0)
    try:  # (one request carrying both: the reads near a tick placed by the pairs)
        moved, _ = on_grid(data, found, model if simulated else replace(model, delay_s=tick), pairs=not simulated)
        if found.grids[0][1].simulated:
            placed = {seg.run: place_reads(seg, found.for_run(seg.run), model) for seg in data.segments}
            baseline = _simulation_ms(data, model)
            best = _simulation_ms(moved, replace(model, delay_s=grid_delay_s(data, found, placed)))
        else:
            baseline = pair_residual_ms(data, model.delay_s, model.time_constant_s)
            best = pair_residual_ms(moved, tick, model.time_constant_s)
    except IdentificationError:
        return None
    if not (best > 0 and baseline / best >= min_gain):
        return None
    return replace(found, gain=baseline / best)


def find_grid_at(
    data: Dataset, model, tick: float, lead_s: float = 0.0, min_gain: float = MIN_GAIN, simulated: bool = False
) -> DriveGrid | None:
    """The drive's tick grid with nominal tick ``tick`` [s] on the host's clock that best explains
    ``data`` under ``model`` (whose ``delay_s`` is about one tick, or up to ``lead_s`` less), or
    None where no grid explains it clearly better than the model's constant delay.

    In each
    window of :data:`WINDOW_S` the phase is the one of :data:`PHASES` (refined
    between its neighbours) whose grid leaves the model's residual
    smallest (its pairs', the command acting one tick after its sample; with a
    command lead, its simulation's, each command acting from its own tick); the phases,
    unwrapped along the run, give the grid's phase and the drive clock's drift
    by a straight-line fit (median-robust). The grid is kept where the refitted
    mean squared residual falls ``min_gain`` times below the constant delay's. The runs
    of a log each start their clock at their first sample: one run at a time here.
    """
    from servobench.bench.identify.joint import pair_residual_ms

    tau = model.time_constant_s
    simulated = simulated or lead_s > 0
    try:
        # the constant delay identified
        baseline = _simulation_ms(data, model) if simulated else pair_residual_ms(data, model.delay_s, tau)
    except IdentificationError:
        return None
    if not simulated:
        model = replace(model, delay_s=tick)
    t_end = max(float(s.t[-1]) for s in data.segments)
    window = max(WINDOW_S, 1.25 * MIN_WINDOW_PAIRS * data.dt_s)  # a slow link: longer windows
    edges = np.arange(0.0, t_end + window, window)
    phases = np.arange(PHASES) * tick / PHASES
    costs = np.full((PHASES, edges.size - 1), np.nan)
    counts = np.zeros(edges.size - 1)
    for i, phase in enumerate(phases):
        sums = np.zeros(edges.size - 1)
        n = np.zeros(edges.size - 1)
        for t_pair, e in _residuals(data, model, DriveGrid(tick, phase, 1.0, 0.0, lead_s, simulated)):
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
            trial = DriveGrid(tick, float(phase), 1.0, drift, lead_s, simulated)
            cost = _grid_cost(data, model, trial)
            if cost < best_cost:
                best_cost, grid = cost, trial
    if grid is None:
        return None
    step = tick / FINE_PHASES
    for phase in grid.phase_s + np.linspace(-step, step, 2 * REFINE_STEPS + 1):
        trial = replace(grid, phase_s=float(phase % tick))
        cost = _grid_cost(data, model, trial)
        if cost < best_cost:
            best_cost, grid = cost, trial
    try:
        moved, _ = on_grid(data, grid) if simulated else on_grid(data, grid, model, pairs=True)
        if simulated:
            best = _simulation_ms(moved, replace(model, delay_s=grid_delay_s(data, grid)))
        else:
            best = pair_residual_ms(moved, tick, tau)
    except IdentificationError:
        return None
    if not (best > 0 and baseline / best >= min_gain):
        return None
    return replace(grid, gain=baseline / best)


def phased_by_placed_pairs(data: Dataset, model, grid: RunGrids) -> RunGrids:
    """``grid`` with each run's phase read again by ``model``'s pairs once they place the reads
    near a tick (:func:`phase_by_placed_pairs`); ``model``: one identified on ``grid`` (under a
    model the constant delay bent, the pairs misplace reads the grid alone puts right)."""
    grids = tuple(
        (run, phase_by_placed_pairs(replace(data, segments=tuple(s for s in data.segments if s.run == run)), model, g))
        for run, g in grid.grids
    )
    return replace(grid, grids=grids)


def phase_by_placed_pairs(data: Dataset, model, grid: DriveGrid) -> DriveGrid:
    """``grid`` with the phase (of :data:`PHASES` over the tick, refined between its neighbours;
    the drift none or ``grid``'s) whose pairs leave the least mean squared residual once the reads
    near a tick are placed by them (:func:`~servobench.bench.identify.pair_placement.place_by_pairs`),
    as the identification places them, where that is :data:`MIN_GAIN` times less than ``grid``'s
    own (where the placement puts every read right from several phases, ``grid`` stays).

    The grid alone puts each read at the tick its logged instant gives; where many brackets
    straddle a tick, the phase that costs least so is off the drive's. A served Modbus TCP drive
    at a 1 ms tick, read at 1 kHz by a host that missed 300 cycles: the grid alone read run 1's
    phase 0.89 ms, the pairs' residual there 2.0e-5 against 7e-12 at 0.93-0.98 ms, and the model
    identified on it fitted 98.86 % with Coulomb 0.76 % off, where 0.95 ms gives 99.999 %.
    """
    from servobench.bench.identify.joint import pair_residual_ms

    def cost(trial: DriveGrid) -> float:
        try:
            moved, _ = on_grid(data, trial, model, pairs=True)
            return pair_residual_ms(moved, trial.tick_s, model.time_constant_s)
        except IdentificationError:
            return math.inf

    own = cost(grid)
    best_cost, best = math.inf, grid
    for drift in {0.0, grid.drift}:
        for phase in np.arange(PHASES) * grid.tick_s / PHASES:
            trial = replace(grid, phase_s=float(phase), drift=drift)
            c = cost(trial)
            if c < best_cost:
                best_cost, best = c, trial
    if not best_cost * MIN_GAIN < own:  # the grid alone's phase serves the pairs as well
        return grid
    step = grid.tick_s / PHASES
    for phase in best.phase_s + np.linspace(-step, step, 2 * PAIR_REFINE_STEPS + 1):
        trial = replace(best, phase_s=float(phase % grid.tick_s))
        c = cost(trial)
        if c < best_cost:
            best_cost, best = c, trial
    return best


#: Steps each side of the best of :data:`PHASES` in :func:`phase_by_placed_pairs`'s refinement.
PAIR_REFINE_STEPS = 4


def _grid_cost(data: Dataset, model, grid: DriveGrid) -> float:
    """Mean squared residual of ``model`` over every run moved onto ``grid``."""
    total, count = 0.0, 0
    for _, e in _residuals(data, model, grid):
        total += float(e @ e)
        count += e.size
    return total / count if count else math.inf


def _residuals(data: Dataset, model, grid: DriveGrid) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per run on ``grid``: the instants [s] and residuals of ``model``: its pairs' with the command
    acting one tick after its sample (``model.delay_s`` that tick), or with a command lead its
    simulation's, each command acting from its own tick (the model's delay set to their mean)."""
    if not grid.simulated:
        return [_model_residuals(onto_grid(s, grid)[0], model, grid.period_s) for s in data.segments]
    moved, _ = on_grid(data, grid)
    model = replace(model, delay_s=grid_delay_s(data, grid))
    return [_simulation_residual(s, model, data.dt_s) for s in moved.segments]


def _simulation_residual(seg: Segment, model, dt_s: float) -> tuple[np.ndarray, np.ndarray]:
    """The instants [s] and residuals of ``model``'s simulation over ``seg``, but for the samples
    of exchanges the host stalled in (:meth:`Segment.stalled_rows`: where they were read is known
    worse than the drive's tick) and those a command sent in one may have moved
    (:meth:`Segment.after_stalled_commands`): no grid can be judged on them. A served Modbus RTU log at
    50 Hz whose host stalled in one switch's exchange (bracket +-3.9 ms against +-1.2 ms) left the
    sample after it 0.05 off under any grid, and that run's 1 ms grid cut the residual 1.15 times
    where the other run's cut it 3e6 times: no grid was kept, M fit 99.41 %."""
    e = _simulated(seg, model, dt_s) - seg.v
    keep = ~seg.stalled_samples(dt_s, model.M, model.B)
    return seg.t[keep], e[keep]


def _simulated(seg: Segment, model, dt_s: float) -> np.ndarray:
    """``model``'s velocity over ``seg`` from its first sample's velocity, its commands' offsets taken in."""
    from servobench.bench.identify.simulation import simulate_velocity

    dt = dt_s if seg.dt_s is None else seg.dt_s
    return simulate_velocity(model, seg.u, dt, float(seg.v[0]), seg.act_offset_s)


def _simulation_ms(data: Dataset, model) -> float:
    """Mean squared simulation residual of ``model`` over every run of ``data``."""
    e = np.concatenate([_simulation_residual(s, model, data.dt_s)[1] for s in data.segments])
    return float(np.mean(e * e)) if e.size else math.inf


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
