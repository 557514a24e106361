"""The compiled plant simulator against the reference loops it was written from.

:class:`~servobench.sim_backend.physics.rich_plant.RichModel` runs the compiled integrator
(:mod:`servobench.sim_backend.physics.kernels`) unless built with ``reference=True``, which
keeps the Python loops (``_run_rigid``, ``_run_gap``, ``_run_spring``); the base plant's reference is
:func:`~servobench.sim_backend.physics.coulomb.simulate_coulomb`. The cases are the
diagnosis benchmark's plants (every library effect, none, and pairs, drawn by
:func:`~servobench.bench.testing.hidden_effects.random_case`) on each of its five inputs,
plus states and calls the simulated drive makes: 78 plant/input cases in all.

The one body and the play give the reference's numbers bit for bit; a spring's reversals
(the motor stopping inside a segment) propagate its linear system over a fraction of the
segment from its modes (complex eigenvalues), where the compiled loop sums in its own order:
there the two agree within rounding (1e-13 seen over 10^4 samples), inside :data:`RTOL`.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from servobench.bench.testing.hidden_effects import case_commands, random_case
from servobench.sim_backend.physics import effects as library
from servobench.sim_backend.physics.compiled import pack_coulomb, run
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState, simulate_coulomb
from servobench.sim_backend.physics.effects import collect_terms
from servobench.sim_backend.physics.rich_plant import RichModel, build_model

#: Largest difference allowed, relative to the largest magnitude of the signal.
RTOL = 1e-12
INPUTS = ("two-level", "sidbe", "square", "sine", "triangle")
PAIRS = (
    ("backlash", "stribeck"),
    ("cogging", "position_friction"),
    ("time_delay", "viscous_asymmetry"),
)
PLANTS = (None, *library.names(), *PAIRS)


def close(new: np.ndarray, old: np.ndarray) -> None:
    scale = max(float(np.max(np.abs(old), initial=0.0)), 1e-300)
    worst = float(np.max(np.abs(new - old), initial=0.0))
    assert np.all(np.isfinite(new)) and worst <= RTOL * scale, (worst, scale)


def both(params: PlantParams) -> tuple[RichModel, RichModel]:
    """The compiled model and the reference model of one plant."""
    return build_model(params), RichModel(params, collect_terms(params), reference=True)


def case(plant, inputs: str):
    rng = np.random.default_rng(zlib.crc32(f"{plant} {inputs}".encode()))
    hidden = random_case(plant, rng, inputs=inputs)
    return hidden.params, [u for _, u in case_commands(hidden, rng)]


@pytest.mark.parametrize("inputs", INPUTS)
@pytest.mark.parametrize("plant", PLANTS, ids=str)
def test_the_compiled_simulation_equals_the_reference(plant, inputs):
    params, runs = case(plant, inputs)
    dt = 1.0 / 500.0
    for u in runs:
        if not params.effects:
            v0, x0, end0 = simulate_coulomb(u, dt, params)
            out_v, out_x, _ = run(
                [pack_coulomb(params, dt)], [[np.r_[0.0, u]]], [(0, 0, u.size, 0)], np.zeros((1, 5))
            )
            close(out_v[0], v0)
            close(out_x[0], x0)
            continue
        new, ref = both(params)
        assert new.packed(dt) is not None, "every library effect compiles"
        v1, x1, end1 = new.simulate(u, dt, PlantState())
        v0, x0, end0 = ref.simulate(u, dt, PlantState())
        close(v1, v0)
        close(x1, x0)
        close(
            np.array([end1.v, end1.x, *new._hidden[2:4]]),
            np.array([end0.v, end0.x, *ref._hidden[2:4]]),
        )
        assert new._hidden[4] == ref._hidden[4]


def _three_windows(plant):
    """A two-level run of ``plant`` cut into three windows: the command, the step, the reference
    model, the compiled model's numbers and the windows' spans."""
    params, runs = case(plant, "two-level")
    dt = 1.0 / 500.0
    new, ref = both(params)
    return runs[1], dt, ref, new.packed(dt), [(0, 300), (300, 620), (620, 1000)]


@pytest.mark.parametrize(
    "plant",
    ("backlash", "stribeck", "time_delay", "resonance", ("cogging", "position_friction")),
    ids=str,
)
def test_windows_primed_and_started_in_motion_equal_the_reference(plant):
    """What the diagnosis does: each window primed with the commands before it and started from
    a measured state, all windows in one call."""
    u, dt, ref, pk, spans = _three_windows(plant)
    starts = [(0.0, 0.0), (0.8, 0.05), (-0.4, -0.02)]
    windows, col = [], 0
    for s, e in spans:
        windows.append((0, s, e - s, col))
        col += e - s
    start = np.array([(v, x, v, x, 0.0) for v, x in starts])
    v_all, x_all, _ = run([pk, pk], [[pk.line(u)], [pk.line(u)]], windows, start)
    for (s, e), (v, x), (_, _, n, o) in zip(spans, starts, windows, strict=True):
        ref.reset()
        ref.prime(u[:s], dt)
        v0, x0, _ = ref.simulate(u[s:e], dt, PlantState(v, x))
        for p in range(2):
            close(v_all[p, o : o + n], v0)
            close(x_all[p, o : o + n], x0)


@pytest.mark.parametrize("plant", ("backlash", "resonance", "stribeck"), ids=str)
def test_windows_that_carry_on_the_second_body_equal_the_reference(plant):
    """What the diagnosis does with contiguous windows: each restarts the measured body at the
    measured state and carries on the play's load and engaged side, or the spring's twist, from
    where the window before ended (:func:`~servobench.sim_backend.physics.kernels.carry_state`)."""
    u, dt, ref, pk, spans = _three_windows(plant)
    whole, _, _ = ref.simulate(u[:1000], dt, PlantState())  # the whole span, no restart
    ref.reset()
    windows = [(0, s, e - s, s) for s, e in spans]
    at = [(float(whole[s]), 0.0) for s, _ in spans]  # the measured body's velocity at each start
    start = np.array([(v, x, v, x, 0.0) for v, x in at])
    carry = np.array([False, True, True])
    v_all, x_all, _ = run([pk], [[pk.line(u)]], windows, start, carry)
    relaxed, _, _ = run([pk], [[pk.line(u)]], windows, start)
    for w, ((s, e), (v, x)) in enumerate(zip(spans, at, strict=True)):
        if carry[w]:
            ref.carry_on(PlantState(v, x))
        else:
            ref.reset()
        ref.prime(u[:s], dt)
        v0, x0, _ = ref.simulate(u[s:e], dt, PlantState(v, x))
        close(v_all[0, s:e], v0)
        close(x_all[0, s:e], x0)
    if plant == "stribeck":  # one body: nothing to carry, the same as restarting
        assert np.array_equal(v_all, relaxed)
        return
    # the second body carried on: the windows follow the whole run (the measured body restarted
    # at its own velocity) where restarting relaxed does not
    carried = np.max(np.abs(v_all[0, 300:1000] - whole[300:1000]))
    restarted = np.max(np.abs(relaxed[0, 300:1000] - whole[300:1000]))
    assert carried < 1e-9 * np.max(np.abs(whole)) < restarted, (carried, restarted)


@pytest.mark.parametrize(
    "plant", ("backlash", "resonance", ("stribeck", "time_delay"), "quantization"), ids=str
)
def test_sample_by_sample_compiled_equals_the_reference(plant):
    """The simulated drive's calls: one sample at a time, the delay line and the play's state
    carried from call to call."""
    params, runs = case(plant, "sine")
    dt = 1.0 / 500.0
    u = runs[0][:400]
    new, ref = both(params)
    new.compiled_from = 1  # compiled however short the call
    state_new = state_ref = PlantState()
    for k in range(u.size):
        v1, x1, state_new = new.simulate(u[k : k + 1], dt, state_new)
        v0, x0, state_ref = ref.simulate(u[k : k + 1], dt, state_ref)
        assert (v1[0], x1[0]) == pytest.approx((v0[0], x0[0]), rel=RTOL, abs=1e-300)
    close(np.array([state_new.v, state_new.x]), np.array([state_ref.v, state_ref.x]))


@pytest.mark.parametrize("modes", [True, False], ids=["modes", "defective"])
def test_a_springs_reversals_run_compiled_on_its_modes(modes):
    """A spring's reversals (the motor stopping inside a segment) propagate its systems from their
    modes inside the compiled loop, without calling the reference back; a model with a defective
    system (no modes) calls the reference's own step back. Both equal the reference."""
    import dataclasses

    from servobench.sim_backend.physics import kernels
    from servobench.sim_backend.physics.compiled import SPRING_SYSTEMS

    assert [kernels.spring_system(*s) for s in SPRING_SYSTEMS] == list(range(6))
    params, runs = case("resonance", "sidbe")
    dt = 1.0 / 500.0
    new, ref = both(params)
    pk = new.packed(dt)
    assert pk.modes.shape == (1, 6 * kernels.MODE_COLS)
    if not modes:  # as a model with a defective system packs
        ipar = pk.ipar.copy()
        ipar[kernels.MODE], ipar[kernels.KEY] = -1, 10**9
        kernels.REVERSALS[10**9] = new
        pk = dataclasses.replace(pk, ipar=ipar, modes=pk.modes[:0], owner=new)
    called, reverse = [0], new._spring_reverse

    def counted(*args):
        called[0] += 1
        return reverse(*args)

    new._spring_reverse = counted
    reversals, step = [0], ref._spring_reverse

    def counted_ref(*args):
        reversals[0] += 1
        return step(*args)

    ref._spring_reverse = counted_ref
    u = runs[1]
    v1, x1, _ = run([pk], [[pk.line(u)]], [(0, 0, u.size, 0)], np.zeros((1, 5)))
    v0, x0, _ = ref.simulate(u, dt, PlantState())
    close(v1[0], v0)
    close(x1[0], x0)
    assert reversals[0] > 20  # the case reverses the motor inside segments
    assert called[0] == (0 if modes else reversals[0])


def test_a_term_that_is_not_data_runs_on_the_reference():
    """A bare callable (a plant outside the library) is integrated by the Python loop."""
    params = PlantParams(effects={"stribeck": {"fs": 0.8, "vs": 0.05}})
    terms = collect_terms(params)
    terms.position_forces.append(lambda x: 0.3 * x)
    model = RichModel(params, terms)
    assert model.packed(1e-3) is None
    v, _, _ = model.simulate(np.full(200, 2.0), 1e-3, PlantState())
    assert np.all(np.isfinite(v)) and v[-1] > 0


def test_the_diagnosis_jacobian_is_least_squares_own():
    """The refit's batched Jacobian equals ``least_squares``'s two-point difference bit for bit."""
    from scipy.optimize._numdiff import approx_derivative

    from servobench.bench.diagnose.refit import DIFF_STEP, _Layout, _Problem

    class Error:  # the residual of a candidate: a smooth function of its parameters
        def residual(self, cand):
            b = cand.base
            t = np.linspace(0.0, 1.0, 50)
            return (
                np.sin(b["M"] * t)
                + b["B"] * t * t
                - b["coulomb_pos"]
                + cand.effects["offset"]["offset"] ** 3
            )

        def residuals(self, cands):
            return [self.residual(c) for c in cands]

    from servobench.bench.diagnose.simulate import Candidate

    cand = Candidate(
        {"M": 0.1, "B": 1.0, "coulomb_pos": 0.4, "coulomb_neg": 0.3}, {"offset": {"offset": 0.05}}
    )
    layout = _Layout(cand, {"offset": {"offset": (-1.0, 1.0)}}, {})
    z0, lo, hi = layout.start()
    z0[2] = hi[2] if np.isfinite(hi[2]) else z0[2]
    problem = _Problem(Error(), layout, lo, hi)
    f0 = problem.fun(z0)
    expected = approx_derivative(
        lambda z: Error().residual(layout.candidate(z)),
        z0,
        method="2-point",
        rel_step=DIFF_STEP,
        f0=f0,
        bounds=(lo, hi),
    )
    assert np.array_equal(problem.jac(z0), expected)


def test_the_compiled_play_operator_equals_the_reference():
    from servobench.sim_backend.physics.effects.backlash import engaged

    def reference(x, gap):
        half = 0.5 * gap
        out = np.zeros(x.size, dtype=bool)
        xl = float(x[0]) if x.size else 0.0
        for i, xi in enumerate(x.tolist()):
            if xi - xl > half:
                xl = xi - half
                out[i] = True
            elif xl - xi > half:
                xl = xi + half
                out[i] = True
        return out

    x = np.cumsum(np.random.default_rng(1).normal(size=5000)) * 0.01
    for gap in (0.0, 0.01, 0.1, 1.0):
        assert np.array_equal(engaged(x, gap), reference(x, gap))
    assert engaged(np.zeros(0), 0.1).size == 0


def test_the_compiled_variable_interval_integrator_equals_its_reference_bit_for_bit():
    """``simulate_variable_dt`` (the drive grid's searches call it thousands of times a log) against
    its loop's source run by the interpreter: random plants with and without breakaway levels,
    commands that stick, break away and reverse, irregular intervals, one interval more than
    needed."""
    from servobench.bench.identify.simulation import (
        simulate_variable_dt,
        simulate_variable_dt_reference,
    )

    rng = np.random.default_rng(0)
    moved = 0
    for i in range(120):
        n = int(rng.integers(1, 600))
        fcp, fcn = rng.uniform(0, 1), rng.uniform(0, 1)
        params = PlantParams(M=rng.uniform(0.005, 0.5), B=rng.uniform(0.2, 3), coulomb_pos=fcp, coulomb_neg=fcn,
                             brk_pos=None if i % 2 else fcp * rng.uniform(1, 1.5),
                             brk_neg=None if i % 2 else fcn * rng.uniform(1, 1.5))  # fmt: skip
        u = np.where(rng.random(n) < 0.3, 0.0, rng.choice([-2, -0.6, -0.3, 0.3, 0.6, 2.0], n) * rng.uniform(0.5, 1.5))
        if i % 3 == 0:
            u = np.repeat(u[: n // 10 + 1], 10)[:n]  # held commands: the axis settles and sticks
        dts = rng.uniform(1e-4, 5e-3, max(n - 1, 0))
        if i % 5 == 0:
            dts = np.concatenate((dts, [1e-3]))
        v0 = float(rng.choice([0.0, 0.5, -0.3]))
        got = simulate_variable_dt(u, dts, params, v0)
        want = simulate_variable_dt_reference(u, dts, params, v0)
        assert np.array_equal(got, want), (i, float(np.max(np.abs(got - want))))
        moved += bool(np.any(want != 0.0))
    assert moved > 100  # the cases move the axis


def test_an_excess_past_its_cut_leaves_the_coulomb_level_as_it_is():
    """:func:`~.kernels.excess_cut`: past the cut the kernels skip the excess's ``exp``; the
    level it would have been added to rounds to itself there, for levels and excesses over
    twelve decades, and a Stribeck plant driven far past its cut still gives the reference's
    numbers bit for bit."""
    from servobench.sim_backend.physics import kernels

    rng = np.random.default_rng(7)
    for _ in range(2000):
        fcp, fcn = 10.0 ** rng.uniform(-4, 4, 2)
        pos, neg = 10.0 ** rng.uniform(-4, 4, 2) * rng.uniform(0, 3, 2)
        cut = kernels.excess_cut(pos, neg, fcp, fcn)
        for z2 in (cut, np.nextafter(cut, np.inf), cut * 1.5 + 1):
            assert fcp + pos * np.exp(-z2) == fcp and -fcn - neg * np.exp(-z2) == -fcn
    assert kernels.excess_cut(1.0, 1.0, 0.0, 0.4) == np.inf  # no level to hide it in
    params, runs = case("stribeck", "square")
    new, ref = both(params)
    inv = 1.0 / params.effects["stribeck"]["vs"]
    cut = kernels.excess_cut(*(params.effects["stribeck"]["fs"],) * 2, params.coulomb_pos,
                             params.coulomb_neg)  # fmt: skip
    for u in runs:
        v1 = new.simulate(u, 1.0 / 500.0, PlantState())[0]
        v0 = ref.simulate(u, 1.0 / 500.0, PlantState())[0]
        assert np.array_equal(v1, v0)
        assert np.mean((v0 * inv) ** 2 > cut) > 0.2  # most samples skip the exp
