"""Reads near a drive tick placed by the model's pairs (one request carries command and sample).

A drive with a 0.25 ms tick, a host cycle of 1 ms whose requests arrive with
a jitter of +-0.15 ms, and a log that knows each arrival only within a bracket
of +-0.1 ms around an instant off the true one by up to 0.08 ms. The truth is
known per read (its tick), so the placement is judged read by read.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from servobench.bench.identify.pair_placement import place_by_pairs
from servobench.bench.identify.simulation import simulate_variable_dt
from servobench.sim_backend.physics.coulomb import PlantParams

TICK = 2.5e-4
PLANT = PlantParams(M=0.01, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def _log(seed: int, noise: float = 0.0):
    rng = np.random.default_rng(seed)
    n = 3000
    arrival = np.arange(n) * 1e-3 + 0.3e-3 + rng.uniform(-0.15e-3, 0.15e-3, n)
    k_true = np.floor(arrival / TICK)
    logged = arrival + rng.uniform(-0.08e-3, 0.08e-3, n)
    u = np.repeat(rng.choice([-2.0, 2.0], n // 20 + 1), 20)[:n]  # switches every 20 ms
    ticks = int(k_true[-1]) + 2
    in_force = np.zeros(ticks)  # the command over [m, m + 1): the last read's whose tick is before m
    for i in range(n):
        in_force[int(k_true[i]) + 1:] = u[i]
    v_tick = simulate_variable_dt(in_force, np.full(ticks - 1, TICK), PLANT, 0.0)
    v = v_tick[k_true.astype(int)] + noise * rng.standard_normal(n)
    return logged, np.full(n, 0.1e-3), u, v, k_true, v_tick


def _cost(k, k_true, v_tick):
    """Squared velocity the misplaced reads put at the wrong tick (0 on a steady stretch)."""
    return float(np.sum((v_tick[k.astype(int)] - v_tick[k_true.astype(int)]) ** 2))


def _place(logged, unc, u, v, params=PLANT):
    k0 = np.floor(logged / TICK)
    return k0, place_by_pairs(logged, unc, u, v, k0, lambda m: np.asarray(m) * TICK, TICK, params)


@pytest.mark.parametrize("seed", [1, 2])
def test_misplaced_reads_in_transients_go_to_their_tick(seed):
    logged, unc, u, v, k_true, v_tick = _log(seed)
    k0, k = _place(logged, unc, u, v)
    assert np.count_nonzero(k0 != k_true) > 100  # the bracket's offset misplaces many reads
    assert np.count_nonzero(k != k_true) < np.count_nonzero(k0 != k_true)
    # the ones left are on steady stretches, where either tick gives the same sample
    assert _cost(k, k_true, v_tick) < 1e-6 * _cost(k0, k_true, v_tick)
    assert np.all(np.diff(k) >= 0)


def test_no_read_leaves_its_bracket():
    logged, unc, u, v, _, _ = _log(3)
    _, k = _place(logged, unc, u, v)
    assert np.all(k * TICK <= logged + unc + 1e-15)
    assert np.all((k + 1) * TICK > logged - unc)


def test_noise_moves_no_read_on_a_steady_axis():
    logged, unc, _, _, _, _ = _log(4)
    u = np.full(logged.size, 2.0)
    v = (2.0 - 0.5) / 1.0 + 0.01 * np.random.default_rng(4).standard_normal(logged.size)
    k0, k = _place(logged, unc, u, v)
    assert np.count_nonzero(k != k0) <= 0.01 * k.size


def test_a_wrong_model_still_beats_the_logged_instants_with_noise():
    logged, unc, u, v, k_true, v_tick = _log(5, noise=0.002)
    biased = PlantParams(M=0.0105, B=1.02, coulomb_pos=0.49, coulomb_neg=0.41)
    k0, k = _place(logged, unc, u, v, biased)
    # the misplacements left are those the noise hides (a step of the transient below its scale)
    assert _cost(k, k_true, v_tick) < 0.2 * _cost(k0, k_true, v_tick)


def test_the_pairs_step_is_the_exact_stick_slip_simulation():
    from servobench.bench.identify.pair_placement import _step

    rng = np.random.default_rng(6)
    plant = PlantParams(M=0.02, B=0.7, coulomb_pos=0.5, coulomb_neg=0.3, brk_pos=0.6, brk_neg=0.35)
    v0 = np.concatenate((rng.uniform(-2, 2, 400), np.zeros(100)))
    u = rng.uniform(-3, 3, 500)
    dt = rng.uniform(0.0, 0.05, 500)
    want = [simulate_variable_dt(np.array([a, 0.0]), np.array([d]), plant, b)[-1]
            for a, d, b in zip(u, dt, v0, strict=True)]
    np.testing.assert_allclose(_step(v0, u, dt, plant), want, rtol=1e-12, atol=1e-14)


def test_a_read_the_host_stalled_on_takes_the_tick_its_pairs_fit():
    logged, unc, u, v, k_true, v_tick = _log(7)
    i = 1500 + int(np.argmax(np.abs(np.diff(v[1500:1600]))))  # a read in a transient
    unc = unc.copy()
    unc[i] = 2.2e-3  # the host knows its instant within 9 ticks either way
    logged = logged.copy()
    logged[i] += 1.5e-3  # and logged it 6 ticks late
    k0, k = _place(logged, unc, u, v)
    assert k0[i] - k_true[i] >= 5
    assert k[i] == k_true[i]
    assert _cost(k, k_true, v_tick) < 1e-6 * _cost(k0, k_true, v_tick)


def test_a_run_whose_every_read_the_host_stalled_on_keeps_its_logged_ticks_quietly():
    """No pair a tick apart clear of stalled reads leaves no residual scale: the reads keep
    their logged ticks, without numpy's warning of an empty median on the user's terminal (a
    served Modbus RTU log's short run printed it)."""
    logged, unc, u, v, _, _ = _log(9)
    logged, u, v = logged[:12], u[:12], v[:12]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        k0, k = _place(logged, np.full(12, 0.5), u, v)  # every bracket +-0.5 s
    assert np.array_equal(k, k0)


def test_the_compiled_path_search_equals_its_numpy_reference():
    """The least-cost placement (compiled: a log's placement runs it tens of times over thousands
    of reads) against the same dynamic programme in numpy, one read at a time: random candidate
    ticks, reads allowed or not, residuals with ties and a NaN; the same ticks every time."""
    from servobench.bench.identify.pair_placement import _viterbi, _viterbi_reference

    rng = np.random.default_rng(0)
    moved = 0
    for i in range(300):
        n, size = int(rng.integers(1, 300)), int(rng.integers(1, 6))
        shifts = np.sort(rng.choice(np.arange(-3, 4), size, replace=False)).astype(float)
        cand = np.cumsum(rng.integers(0, 3, n)).astype(float)[:, None] + shifts[None, :]
        allowed = rng.random((n, size)) < 0.8
        allowed[np.arange(n), rng.integers(0, size, n)] = True
        e = rng.normal(size=(n - 1, size, size))
        if i % 4 == 0:
            e = np.round(e)  # equal costs: the first of equal minima, as np.argmin
        if i % 7 == 0 and e.size:
            e.flat[rng.integers(0, e.size)] = np.nan
        bar = float(rng.uniform(0.0, 3.0))
        got = _viterbi(cand, allowed, e, shifts, bar)
        want = _viterbi_reference(cand, allowed, e, shifts, bar)
        assert np.array_equal(got, want), i
        moved += bool(np.any(want != cand[np.arange(n), np.argmin(np.abs(shifts))]))
    assert moved > 100  # the cases move reads off their logged tick


def test_only_the_pairs_of_allowed_ticks_are_computed_and_only_they_decide():
    """A read's bracket holds a few of its candidate ticks, so the pair residuals are computed only
    where both reads' candidates are allowed (compiled): there they equal the full computation in
    numpy within rounding, elsewhere 0,
    and the least-cost path is the one the full residuals give (it never reads a pair with an end
    its bracket rules out)."""
    from servobench.bench.identify.pair_placement import (
        _allowed_pair_errors,
        _pair_errors,
        _viterbi,
    )

    logged, _, u, v, _, _ = _log(3)
    rng = np.random.default_rng(1)
    shifts = np.arange(-3.0, 4.0)
    cand = np.floor(logged / TICK)[:, None] + shifts[None, :]
    allowed = rng.random(cand.shape) < 0.35
    allowed[:, 3] = True
    u_first = np.concatenate(([0.0], u[:-2]))
    full = _pair_errors(cand[:-1, :, None], cand[1:, None, :], v[:-1], v[1:], u_first, u[:-1], TICK, PLANT)
    got = _allowed_pair_errors(cand, allowed, v, u_first, u[:-1], TICK, PLANT)
    both = allowed[:-1, :, None] & allowed[1:, None, :]
    assert np.isfinite(full).all() and 0.1 < both.mean() < 0.4
    # compiled: equal within rounding (its exp and log are the C library's, numpy's its own)
    assert np.all(np.abs(got[both] - full[both]) <= 1e-12 * (1.0 + np.abs(full[both]))) and not got[~both].any()
    for bar in (0.0, 1e-4, 1e-2):
        assert np.array_equal(_viterbi(cand, allowed, got, shifts, bar), _viterbi(cand, allowed, full, shifts, bar))


def test_the_compiled_placement_of_stalled_reads_equals_its_numpy_reference():
    """Reads the host stalled on are placed one at a time, each among the ticks its bracket holds
    (compiled: a loaded host stalls on thousands). Against the numpy reference, read by read, the
    one before as already placed: random brackets of 1-9 ticks over the test's log, noisy and
    exact, with a plant that breaks away above its Coulomb level; the same ticks every time."""
    from servobench.bench.identify.pair_placement import _best_alone, _place_alone, _plant

    rng = np.random.default_rng(4)
    moved = 0
    for seed, noise in ((5, 0.0), (6, 0.002), (7, 0.02)):
        logged, _, u, v, _, _ = _log(seed, noise)
        for params in (PLANT, PlantParams(M=0.01, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4, brk_pos=0.7,
                                          brk_neg=0.6)):  # fmt: skip
            k = np.floor(logged / TICK)
            wide = np.flatnonzero(rng.random(k.size) < 0.3)
            first = k - rng.integers(0, 5, k.size)
            last = k + rng.integers(0, 5, k.size)
            want = k.copy()
            for i in wide.tolist():
                want[i] = _best_alone(i, want, first[i], last[i], u, v, TICK, params)
            got = k.copy()
            _place_alone(wide, got, first, last, u, v, TICK, *_plant(params))
            assert np.array_equal(got, want), (seed, noise)
            moved += int(np.count_nonzero(want != k))
    assert moved > 500  # the cases move reads off their logged tick


def test_the_posterior_draws_follow_the_exact_posterior_of_a_small_chain():
    """The timing figure's draws place the reads by a draw from the pairs' posterior (forward
    filtering, backward sampling, compiled). On chains of 4 reads with 3 candidate ticks each,
    random costs and reads not allowed everywhere, the frequency of every path over 20 000 draws
    matches the posterior enumerated path by path (``exp(-cost / T)`` of :func:`_viterbi`'s cost)."""
    import itertools

    from servobench.bench.identify.pair_placement import _posterior, _viterbi_costs

    rng = np.random.default_rng(5)
    for case in range(3):
        n, size = 4, 3
        shifts = np.array([-1.0, 0.0, 1.0])
        cand = np.arange(n, dtype=float)[:, None] * 2.0 + shifts[None, :]
        allowed = rng.random((n, size)) < 0.8
        allowed[:, 1] = True
        e = rng.normal(0.0, 1.0, (n - 1, size, size))
        bar, temperature = 0.7, 2.0
        moved, switch, pair = _viterbi_costs(cand, e, shifts, bar)
        exact = {}
        for path in itertools.product(range(size), repeat=n):
            if not all(allowed[j, s] for j, s in enumerate(path)):
                continue
            cost = sum(moved[s] for s in path) + sum(pair[j - 1, path[j - 1], path[j]] + switch[path[j - 1], path[j]]
                                                     for j in range(1, n))  # fmt: skip
            exact[path] = np.exp(-cost / temperature)
        total = sum(exact.values())
        draws = 20_000
        seen: dict[tuple, int] = {}
        for _ in range(draws):
            ticks = _posterior(cand, allowed, e, shifts, bar, temperature, rng)
            path = tuple(int(np.flatnonzero(cand[j] == ticks[j])[0]) for j in range(n))
            seen[path] = seen.get(path, 0) + 1
        assert set(seen) <= set(exact), case
        for path, weight in exact.items():
            p = weight / total
            assert abs(seen.get(path, 0) / draws - p) <= 4.0 * np.sqrt(p * (1 - p) / draws) + 1e-3, (case, path, p)


def test_reads_the_pairs_decide_keep_their_tick_in_every_posterior_draw():
    """A noise-free log: the pairs decide every read in a transient, so each posterior draw gives
    the least-cost ticks there (where a steady stretch leaves a read free, both ticks hold one
    sample and the draw costs the model nothing); with noise the draws move reads the pairs leave
    in doubt, and only those."""
    logged, unc, u, v, k_true, v_tick = _log(1)
    k0 = np.floor(logged / TICK)
    grid = lambda m: np.asarray(m) * TICK  # noqa: E731
    mode = place_by_pairs(logged, unc, u, v, k0, grid, TICK, PLANT)
    rng = np.random.default_rng(0)
    for _ in range(3):
        drawn = place_by_pairs(logged, unc, u, v, k0, grid, TICK, PLANT, rng)
        assert np.all(np.diff(drawn) >= 0)
        assert _cost(drawn, mode, v_tick) < 1e-9
    noisy = _log(2, noise=0.02)
    k0 = np.floor(noisy[0] / TICK)
    mode = place_by_pairs(*noisy[:4], k0, grid, TICK, PLANT)
    moved = [place_by_pairs(*noisy[:4], k0, grid, TICK, PLANT, rng) != mode for _ in range(3)]
    assert 0 < np.mean(moved) < 0.2  # some reads move, most keep the mode's tick

