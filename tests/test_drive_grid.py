"""The drive's tick located on the host's clock from a log without stamps (issue 28).

The reference is built independently of :mod:`servobench.bench.identify.drive_grid`:
a drive that samples at its last tick before each request and acts from the
next, simulated on its own tick grid (exact zero-order hold per tick), read by
a host whose requests jitter across the drive's ticks. Each run's clock starts
at its own first sample, so its ticks lie at a phase of their own; where the
command goes ahead of its query (a serial link), it acts from the first tick
after it arrived.
"""

from __future__ import annotations

import numpy as np
import pytest

from servobench.bench.identify.auto import identify_data
from servobench.bench.identify.dataset import Dataset, Segment
from servobench.bench.identify.drive_grid import DriveGrid, find_drive_grid, on_grid
from servobench.bench.model.servo import ServoModel

TRUE = ServoModel(0.01, 1.0, 0.5, 0.4)
TICK = 1e-3


def _host_log(phase_s: float, seed: int, jitter_s: float = 0.2e-3, n: int = 4000,
              drift: float = 0.0) -> tuple[Dataset, list]:  # fmt: skip
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 1e-3
    s = sum(np.sin(2 * np.pi * f * t + p) for f, p in zip((1.0, 3.0, 7.0), rng.uniform(0, 6, 3), strict=True))
    segments, sampled = [], []
    for run, scale in ((1, 1.0), (2, 0.8)):
        u = 2.0 * scale * np.sign(s)
        arrive = t + 1.3e-3 + rng.uniform(-jitter_s, jitter_s, n)  # the request reaches the drive
        n_sample = np.floor(((1.0 - drift) * arrive - phase_s) / TICK).astype(int)  # its last tick
        ticks = int(n_sample[-1]) + 2
        u_tick = np.zeros(ticks)  # the command in force over each tick: the last one that arrived
        for k in range(n):
            u_tick[n_sample[k] + 1 :] = u[k]
        v_tick = TRUE.simulate(u_tick, (1.0 - drift) / TICK).v  # the drive's ticks on the log's clock
        v = v_tick[n_sample]
        segments.append(Segment(run, arrive, u, v, 1000.0, np.diff(arrive), t_unc=np.full(n, 0.05e-3)))
        sampled.append(n_sample)
    return Dataset(tuple(segments), 1000.0), sampled


# requests reach the drive 0.1-0.5 ms past each host millisecond: at 0.25 and 0.42 ms a quarter of
# them cross one of its ticks; at 0.8 ms none does, but each sample's lag still varies by 0.4 ms
@pytest.mark.parametrize("phase_s", [0.25e-3, 0.42e-3, 0.8e-3])
def test_the_grid_is_found_and_the_samples_go_back_onto_their_ticks(phase_s):
    data, sampled = _host_log(phase_s, seed=int(phase_s * 1e5))
    first, result = _located_and_exact(data, sampled, drift=0.0)
    assert result.model.delay_s == pytest.approx(TICK, abs=0.02e-3)
    assert result.fit_percent > 99.9
    # the constant delay alone is clearly worse on the same log
    assert first.fit_percent < result.fit_percent


@pytest.mark.parametrize("phase_s", [0.25e-3, 0.8e-3])
def test_a_drive_clock_that_drifts_keeps_every_read_on_its_tick(phase_s):
    """A drive crystal 50 ppm fast on the host's (0.2 ms over a 4 s run). At a phase of 0.25 ms the
    reads cross its ticks as the phase slides: the drift is located within a tenth. At 0.8 ms no read
    crosses one: every drift places them alike, and the grid keeps none. Either way every read is on
    its tick and the model exact. (Drifts of 100 ppm and more are located far less well: open.)"""
    data, sampled = _host_log(phase_s, seed=int(phase_s * 1e5) + 1, drift=50e-6)
    _located_and_exact(data, sampled, drift=50e-6 if phase_s < 0.5e-3 else 0.0)


def _located_and_exact(data: Dataset, sampled: list, drift: float):
    """The grid found under the first (constant-delay) model: each run's drift ``drift`` (within a
    tenth; 0 within 1 ppm), every read on the tick it was sampled at (the phase itself is known only
    to within the gap the reads leave between ticks), and the model identified on it exact.
    Returns the first and the final identification."""
    first = identify_data(data, "joint")
    # with the delay's 1 sigma, as ``identify`` does: the constant delay of a log whose reads
    # straddle the ticks may sit more than a twentieth from the tick (0.928 +- 0.049 ms here)
    grid = find_drive_grid(data, first.model, float(first.std.get("delay_s") or 0.0))
    assert grid is not None and grid.tick_s == TICK
    for seg, ticks in zip(data.segments, sampled, strict=True):
        located = grid.for_run(seg.run).drift
        assert located == pytest.approx(drift, rel=0.1, abs=1e-6)
        offset = grid.for_run(seg.run).index(seg.t) - ticks  # one whole number of ticks for every read
        assert np.mean(offset == np.median(offset)) > 0.99
    moved, _ = on_grid(data, grid)
    result = identify_data(moved, "joint")
    for got, want in ((result.model.M, 0.01), (result.model.B, 1.0), (result.model.coulomb_pos, 0.5),
                      (result.model.coulomb_neg, 0.4)):  # fmt: skip
        assert got == pytest.approx(want, rel=1e-3)
    return first, result


def test_a_drive_that_samples_at_the_request_has_no_grid():
    rng = np.random.default_rng(3)
    n = 3000
    t = np.arange(n) * 1e-3 + rng.uniform(-0.1e-3, 0.1e-3, n)
    u = 2.0 * np.sign(np.sin(2 * np.pi * 2.0 * t))
    model = ServoModel(0.01, 1.0, 0.5, 0.4, delay_s=0.3e-3)
    from servobench.bench.identify.simulation import simulate_velocity

    v = simulate_velocity(model, u, np.diff(t))
    data = Dataset((Segment(1, t, u, v, 1000.0, np.diff(t), t_unc=np.full(n, 0.05e-3)),), 1000.0)
    assert find_drive_grid(data, identify_data(data, "joint").model) is None  # 0.3 ms is no tick


def test_a_grid_maps_instants_to_ticks_with_drift():
    g = DriveGrid(1e-3, 0.2e-3, 2.0, drift=50e-6)
    n = g.index(np.array([0.0, 0.00021, 1.0]))
    assert n.tolist() == [-1.0, 0.0, 999.0]
    assert g.instant(np.array([0.0]))[0] == pytest.approx(0.2e-3 / (1 - 50e-6))


def _serial_log(seed: int, lead_s: float, tick: float, n: int = 1600, fs: float = 200.0,
                wire_lead_s: float | None = None, arrival_phase: float | None = None,
                late_s: float = 0.0, t_unc_s: float = 0.05e-3, jitter_s: float = 0.05e-3):  # fmt: skip
    """Two runs at ``fs`` whose commands reach the drive ``wire_lead_s`` (default ``lead_s``, the
    lead the log states) before their queries; each run's clock starts at its first query, at a
    phase of the drive's ticks of its own (or one that puts each command's arrival
    ``arrival_phase`` ticks past a tick). The host logs each query ``late_s`` after the drive
    read it (its bracket's middle, half-width ``t_unc_s``: a port whose latency is the reply's
    more than the request's). The drive's record: each changed command's action tick minus its
    sample tick, mean over the changes (``mean_change_delay_s``: a repeat acts alike from
    either tick)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    s = sum(np.sin(2 * np.pi * f * t + p) for f, p in zip((1.0, 3.0, 7.0), rng.uniform(0, 6, 3), strict=True))
    segments, delays = [], []
    for run, scale in ((1, 1.0), (2, 0.9)):
        u = 2.0 * scale * np.sign(s)
        wire = lead_s if wire_lead_s is None else wire_lead_s
        phase = rng.uniform(0.0, tick)
        if arrival_phase is not None:  # ticks at k T + phase; arrivals at t + tick - wire
            phase = (tick - wire - arrival_phase * tick) % tick
        query = t + tick + rng.uniform(-jitter_s, jitter_s, n)  # the query reaches the drive
        n_sample = np.floor((query - phase) / tick).astype(int)
        arrival = query - wire
        if wire_lead_s is not None:  # the command's own wire time varies apart from the query's
            arrival = arrival + rng.uniform(-0.04e-3, 0.04e-3, n)
        n_act = np.floor((arrival - phase) / tick).astype(int) + 1  # first tick after arrival
        ticks = int(n_act[-1]) + 2
        u_tick = np.zeros(ticks)
        for k in range(n):
            u_tick[n_act[k] :] = u[k]
        v = TRUE.simulate(u_tick, 1.0 / tick).v[n_sample]
        logged = query + late_s - query[0]
        segments.append(Segment(run, logged, u, v, fs, np.diff(logged), t_unc=np.full(n, t_unc_s)))
        change = np.concatenate(([True], u[1:] != u[:-1]))
        delays.append(((n_act - n_sample) * tick)[change])
    data = Dataset(tuple(segments), fs, min_delay_s=-lead_s)
    return data, float(np.mean(np.concatenate(delays)))


@pytest.mark.parametrize(("seed", "tick"), [(1, 1e-3), (2, 2e-3)])
def test_with_a_command_lead_each_command_acts_from_its_own_tick(seed, tick):
    # the command's lead (0.35 ms) puts a tick between command and query for some rows: those
    # act in the sample's own tick, the others a tick later; no constant delay holds both
    data, record = _serial_log(seed, 0.35e-3, tick)
    first = identify_data(data, "joint")
    grid = find_drive_grid(data, first.model, first.std.get("delay_s", 0.0))
    assert grid is not None and grid.tick_s == tick and grid.lead_s == 0.35e-3
    moved, _ = on_grid(data, grid)
    offsets = np.concatenate([s.act_offset_s for s in moved.segments])  # around the mean delay
    u = np.concatenate([s.u for s in moved.segments])
    changes = np.concatenate([[True, *(s.u[1:] != s.u[:-1])] for s in moved.segments])
    assert u.size == offsets.size
    # the mean is the changes' (a repeat acts alike from either tick)
    assert np.mean(offsets[changes]) == pytest.approx(0.0, abs=1e-12) and np.ptp(offsets) == pytest.approx(tick)
    result = identify_data(moved, "joint")
    for got, want in ((result.model.M, 0.01), (result.model.B, 1.0), (result.model.coulomb_pos, 0.5),
                      (result.model.coulomb_neg, 0.4)):  # fmt: skip
        assert got == pytest.approx(want, rel=2e-3)
    assert result.model.delay_s == pytest.approx(record, abs=0.02e-3)
    assert result.fit_percent > 99.9
    assert first.fit_percent < result.fit_percent


def test_a_command_that_arrives_at_a_tick_acts_where_the_simulation_puts_it():
    # the wire's lead is 0.30 ms (+-0.04 ms of its own), the log states 0.35 ms, and every command
    # reaches the drive within 0.1 ms of a tick: whether it acted at that tick or the next is
    # read from the data
    data, record = _serial_log(5, 0.35e-3, 1e-3, wire_lead_s=0.30e-3, arrival_phase=0.0)
    first = identify_data(data, "joint")
    grid = find_drive_grid(data, first.model, first.std.get("delay_s", 0.0), min_gain=1.0)
    assert grid is not None and grid.tick_s == 1e-3
    naive, _ = on_grid(data, grid)  # each action from the stated lead alone
    placed, _ = on_grid(data, grid, first.model)
    result = identify_data(placed, "joint")
    assert identify_data(naive, "joint").fit_percent < result.fit_percent
    for got, want in ((result.model.M, 0.01), (result.model.B, 1.0), (result.model.coulomb_pos, 0.5),
                      (result.model.coulomb_neg, 0.4)):  # fmt: skip
        assert got == pytest.approx(want, rel=2e-3)
    # the commands that repeat the one before show nothing of their tick: their share of the mean
    # delay comes from the changes' (56 of them: +-0.07 ms), within the issue's tenth of a tick
    assert result.model.delay_s == pytest.approx(record, abs=0.1e-3)
    assert result.fit_percent > 99.5


@pytest.mark.parametrize("seed", [8, 10])  # (14 passed too: dropped for the suite's 10 minutes)
def test_reads_off_the_middle_of_their_bracket_go_to_the_tick_the_transients_show(seed):
    # the drive reads each query 0.11 ms (+-0.125 ms) past one of its ticks, and the host's
    # bracket (+-0.2 ms) has its middle 0.11 ms before the read (a port whose latency is the
    # request's more than the reply's): the middles straddle the tick. A changed command's own
    # read comes after a held command (a steady axis), where the two ticks simulate alike; the
    # reads in the transients, which the simulation decides, tell on which side the reads fall.
    # Before, the steady reads took the noise's side: the delay 0.25-0.47 ms off the drive's
    # record on these seeds (as on served serial drives under load), now within 0.02 ms
    from servobench.bench.identify.auto import identify
    from servobench.bench.log.io import ExperimentLog, RunData

    data, record = _serial_log(seed, 0.35e-3, 1e-3, arrival_phase=0.76, late_s=-0.11e-3, t_unc_s=0.2e-3,
                               jitter_s=0.125e-3)  # fmt: skip
    runs = tuple(RunData(s.run, s.t, s.u, s.v, None, {"t_unc": s.t_unc}) for s in data.segments)
    log = ExperimentLog(runs, {"command_lead_s": "0.00035", "pace": "real", "clock_source": "host"},
                        200.0, True, "serial log")  # fmt: skip
    again = identify(log)  # as sidbe does: every nominal tick tried, the best refit kept
    assert any("control tick (1 ms)" in n for n in again.notes), again.notes
    assert again.model.delay_s == pytest.approx(record, abs=0.05e-3)
    for got, want in ((again.model.M, 0.01), (again.model.B, 1.0), (again.model.coulomb_pos, 0.5),
                      (again.model.coulomb_neg, 0.4)):  # fmt: skip
        assert got == pytest.approx(want, rel=1e-3)


def test_a_stalled_read_is_left_out_of_the_verification_fit():
    from dataclasses import replace

    from servobench.bench.identify.verify import verify

    data, _ = _serial_log(1, 0.35e-3, 2e-3)
    seg = data.segments[0]
    v = seg.v.copy()
    v[700] += 1.0  # a read taken somewhere in a 20 ms stall: its instant is unknown
    unc = seg.t_unc.copy()
    unc[700] = 10e-3
    stalled = replace(data, segments=(replace(seg, v=v, t_unc=unc), *data.segments[1:]))
    model = ServoModel(0.01, 1.0, 0.5, 0.4, delay_s=1.5e-3)
    ver = verify(model, stalled)
    assert ver.set_aside == 1
    assert ver.fit_percent > verify(model, replace(stalled, segments=(replace(seg, v=v),
                                                                      *data.segments[1:]))).fit_percent  # fmt: skip
