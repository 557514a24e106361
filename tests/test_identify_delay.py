"""The drive's action delay (issue 28): simulated exactly, identified jointly with the plant.

A command logged at ``t_k`` acts over ``[t_k + d, t_{k+1} + d)``. The references
here are independent of :mod:`servobench.bench.identify.delay`: a ten times
finer zero-order hold with the command shifted by whole fine steps, and the
plain first-order recursion over the pieces of each interval.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from servobench.bench.identify.dataset import (
    Dataset,
    Segment,
    merge_repeated,
    merge_unchanged,
    prepare,
)
from servobench.bench.identify.delay import effective_command, merged_grid, split_delay
from servobench.bench.identify.joint import identify_joint
from servobench.bench.identify.simulation import simulate_velocity
from servobench.bench.log.io import RunData, parse_log_text
from servobench.bench.model.servo import ServoModel

FS = 1000.0
PLANT = dict(M=0.01, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def _command(n: int, amplitude: float = 2.0, seed: int = 0) -> np.ndarray:
    t = np.arange(n) / FS
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0, 2 * np.pi, 3)
    s = sum(np.sin(2 * np.pi * f * t + p) for f, p in zip((1.0, 3.0, 7.0), phases, strict=True))
    return amplitude * np.sign(s)


def test_fractional_delay_matches_a_finer_zero_order_hold():
    u = _command(3000) * (0.3 + np.random.default_rng(1).random(3000))
    fine = 10
    for shift in (3, 4, 10, 17):  # 0.3, 0.4, 1.0, 1.7 samples
        u_fine = np.concatenate((np.zeros(shift), np.repeat(u, fine)[:-shift]))
        reference = simulate_velocity(ServoModel(**PLANT), u_fine, 1.0 / (FS * fine))[::fine]
        delayed = simulate_velocity(ServoModel(**PLANT, delay_s=shift / (FS * fine)), u, 1.0 / FS)
        assert np.max(np.abs(delayed - reference)) < 1e-12
        r = ServoModel(**PLANT, delay_s=shift / (FS * fine)).simulate(u, FS)
        assert np.max(np.abs(r.v - reference)) < 1e-12


def test_effective_command_is_the_first_order_response_to_the_pieces():
    rng = np.random.default_rng(2)
    u = rng.normal(size=400)
    dts = 1e-3 * (1.0 + 0.3 * rng.random(399))
    tau, d = 0.01, 0.00137
    u_eff = effective_command(u, dts, d, tau)
    u_m, dt_m, rows = merged_grid(u, dts, d)
    # the plain recursion over the pieces: v' = exp(-h/tau) v + (1 - exp(-h/tau)) u_piece
    v = np.zeros(u_m.size)
    for i in range(u_m.size - 1):
        a = np.exp(-dt_m[i] / tau)
        v[i + 1] = a * v[i] + (1 - a) * u_m[i]
    vs = v[rows]
    a = np.exp(-dts / tau)
    assert np.max(np.abs(vs[1:] - (a * vs[:-1] + (1 - a) * u_eff))) < 1e-12
    assert split_delay(0.00137, 1e-3) == (1, pytest.approx(0.37))


@pytest.mark.parametrize("cycles", [-2.6, -1.0, -0.3, 0.37, 1.0, 1.0 + 1e-12, 2.0 - 1e-12, 2.5, 3.999])
def test_effective_command_on_one_interval_is_the_merged_grids(cycles):
    """The closed form for one sample interval (no offsets) against the merged grid's pieces
    (the general path, taken with zero offsets)."""
    rng = np.random.default_rng(int(abs(cycles) * 1000))
    u = np.sign(rng.normal(size=300)) * 2.0 + 0.1 * rng.normal(size=300)
    for tau in (1e-4, 0.01, 10.0):
        for before in (0.0, 0.7):
            fast = effective_command(u, 1e-3, cycles * 1e-3, tau, before)
            pieces = effective_command(u, 1e-3, cycles * 1e-3, tau, before, offsets_s=np.zeros(u.size))
            assert fast.shape == (u.size - 1,)
            assert np.max(np.abs(fast - pieces)) < 1e-11


@pytest.mark.parametrize("cycles", [-0.3, 0.37, 1.6])
def test_effective_command_without_viscous_friction_is_the_duration_weighted_mean(cycles):
    """An infinite time constant (``B = 0``: a diagnosis's base with the viscous term gone): the
    weights' limit, each piece by its duration, on both paths, without a warning."""
    rng = np.random.default_rng(7)
    u = rng.normal(size=50)
    m, f = split_delay(cycles * 1e-3, 1e-3)
    padded = np.concatenate(([0.3], u))
    k = np.arange(u.size - 1)
    before = padded[np.clip(k - m - 1, -1, u.size - 1) + 1]
    now = padded[np.clip(k - m, -1, u.size - 1) + 1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fast = effective_command(u, 1e-3, cycles * 1e-3, np.inf, 0.3)
        pieces = effective_command(u, 1e-3, cycles * 1e-3, np.inf, 0.3, offsets_s=np.zeros(u.size))
    assert np.max(np.abs(fast - (f * before + (1 - f) * now))) < 1e-12
    assert np.max(np.abs(pieces - fast)) < 1e-12


@pytest.mark.parametrize("delay_samples", [0.0, 0.37, 1.0, 1.6])
def test_joint_identifies_the_delay_exactly_on_noise_free_data(delay_samples):
    n = 6000
    true = ServoModel(**PLANT, delay_s=delay_samples / FS)
    segments = []
    for run, scale in ((1, 1.0), (2, 0.8)):
        u = _command(n) * scale
        segments.append(Segment(run, np.arange(n) / FS, u, simulate_velocity(true, u, 1 / FS), FS))
    est = identify_joint(Dataset(tuple(segments), FS))
    m = est.model
    for got, want in ((m.M, true.M), (m.B, true.B), (m.coulomb_pos, 0.5), (m.coulomb_neg, 0.4)):
        assert got == pytest.approx(want, rel=1e-7)
    assert m.delay_s == pytest.approx(true.delay_s, abs=1e-9)
    assert "delay_s" in est.std


def test_joint_delay_with_noise_is_within_its_error_bar():
    n = 8000
    true = ServoModel(**PLANT, delay_s=1.0e-3)
    rng = np.random.default_rng(5)
    errors = []
    for seed in range(4):
        segments = []
        for run, scale in ((1, 1.0), (2, 0.8)):
            u = _command(n, seed=seed) * scale
            v = simulate_velocity(true, u, 1 / FS) + 0.01 * rng.standard_normal(n)
            segments.append(Segment(run, np.arange(n) / FS, u, v, FS))
        est = identify_joint(Dataset(tuple(segments), FS))
        sigma = est.std["delay_s"]
        assert 0 < sigma < 0.05e-3
        errors.append((est.model.delay_s - true.delay_s) / sigma)
        assert pytest.approx(true.M, rel=0.01) == est.model.M
        assert est.model.coulomb_neg == pytest.approx(0.4, rel=0.01)
    assert max(abs(e) for e in errors) < 4.0


def test_a_tick_read_twice_is_one_sample_with_the_last_command():
    t = np.array([0.0, 0.001, 0.001, 0.002, 0.003, 0.003, 0.003, 0.004])
    u = np.arange(8.0)
    v = np.array([0.0, 1.0, 1.0, 2.0, 3.0, 3.0, 3.0, 4.0])
    run = RunData(1, t, u, v, None, {"t_unc": np.zeros(8)})
    merged, repeated = merge_repeated(run)
    assert repeated == 3
    assert merged.t.tolist() == [0.0, 0.001, 0.002, 0.003, 0.004]
    assert merged.v.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert merged.u.tolist() == [0.0, 2.0, 3.0, 6.0, 7.0]  # the last command of each tick acts
    assert merged.extra["t_unc"].size == 5
    assert merge_repeated(RunData(1, np.arange(4.0), u[:4], v[:4]))[1] == 0


def test_a_stale_read_of_a_moving_axis_is_one_sample_without_stamps():
    t = np.arange(6) * 1e-3
    v = np.array([5.0, 5.0, 5.0, 5.0, 6.0, 6.0])
    x = np.array([0.0, 0.001, 0.001, 0.002, 0.003, 0.005])  # row 2 repeats row 1 while moving
    run = RunData(1, t, np.arange(6.0), v, x, {"t_unc": np.full(6, 1e-4)})
    merged, stale = merge_unchanged(run)
    assert stale == 1
    assert merged.t.tolist() == [0.0, 0.001, 0.003, 0.004, 0.005]
    assert merged.u.tolist() == [0.0, 2.0, 3.0, 4.0, 5.0]
    # at rest, or slower than two encoder steps per interval, equal reads are kept
    slow = RunData(1, t, np.zeros(6), np.full(6, 0.1), np.array([0, 0, 0, 1e-3, 1e-3, 2e-3]))
    assert merge_unchanged(slow)[1] == 0


def test_a_delay_that_only_zero_crossing_intervals_show_is_read_from_the_simulation():
    # a slow cycle against the plant: every command switch reverses the axis inside its own
    # interval, so no sample pair of one velocity sign holds a switch and the pairs fit any delay
    fs, n = 100.0, 2400
    true = ServoModel(**PLANT, delay_s=1.0e-3)
    segments = []
    for run, scale in ((1, 1.0), (2, 0.8)):
        t = np.arange(n) / fs
        u = 2.0 * scale * np.sign(np.sin(2 * np.pi * 1.0 * t) + 0.5 * np.sin(2 * np.pi * 3.0 * t + 1.0))
        segments.append(Segment(run, t, u, simulate_velocity(true, u, 1 / fs), fs))
    est = identify_joint(Dataset(tuple(segments), fs))
    assert est.model.delay_s == pytest.approx(1.0e-3, abs=1e-7)
    assert pytest.approx(0.01, rel=1e-6) == est.model.M and est.model.coulomb_neg == pytest.approx(0.4, rel=1e-6)


def _late_sample_log(with_act: bool) -> str:
    """A stamped log of a pair on a 1 ms tick where, at every other switch, the host read the
    sample a tick after the one its command took force at (an EtherCAT host that woke late): the
    row's ``t`` is the later tick's, its ``t_act`` (where given) the tick the command acted from,
    and the next command acts from the tick after the sample."""
    n = 4000
    lines = ["# fs = 1000", "# clock_source = drive", "run,t,u,v,x" + (",t_act" if with_act else "")]
    for run, scale in ((1, 1.0), (2, 0.9)):
        u = _command(n) * scale
        late = set((np.flatnonzero(np.diff(u) != 0) + 1)[::2].tolist())
        acts, samples, tick = np.empty(n, dtype=int), np.empty(n, dtype=int), 0
        for j in range(n):
            acts[j], samples[j] = tick, tick + (j in late)
            tick = samples[j] + 1
        u_ticks = u[np.searchsorted(acts, np.arange(tick), side="right") - 1]  # in force per tick
        v = simulate_velocity(ServoModel(**PLANT), u_ticks, 1 / FS)  # (no delay: plain stepping)
        x = np.concatenate(([0.0], np.cumsum(v[:-1] / FS)))
        for j in range(n):
            k = samples[j]
            act = f",{float(acts[j] / FS)!r}" if with_act else ""
            lines.append(f"{run},{float(k / FS)!r},{float(u[j])!r},{float(v[k])!r},{float(x[k])!r}{act}")
    return "\n".join(lines) + "\n"


def test_a_command_the_log_says_took_force_before_its_sample_acts_from_there():
    """``t_act`` (an EtherCAT DC-synchronous slave's, where the host read a later SYNC0 event's
    sample) moves each such command's action back to where it took force: the model is exact;
    taken to act from the row's instant, the same log gives M 8 % off."""
    data = prepare(parse_log_text(_late_sample_log(True)))
    assert any("took force before their row's sample" in note for note in data.notes)
    assert np.count_nonzero(np.isclose(data.segments[0].act_offset_s, -1e-3)) > 10
    m = identify_joint(data).model
    for got, want in ((m.M, 0.01), (m.B, 1.0), (m.coulomb_pos, 0.5), (m.coulomb_neg, 0.4)):
        assert got == pytest.approx(want, rel=1e-6)
    assert abs(m.delay_s) < 1e-8
    blind = identify_joint(prepare(parse_log_text(_late_sample_log(False)))).model
    assert abs(blind.M / 0.01 - 1) > 0.02
