"""Each effect's simulation: against exact transforms, analytic responses and fine-step references."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.sim_backend.physics.plant import Plant, PlantParams, PlantState, simulate_coulomb
from servobench.sim_backend.physics.rich_plant import build_model

DT = 1e-3
BASE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def command(seed: int = 3, n: int = 1500) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.choice([-2.5, 2.5], n // 50), 50) * rng.uniform(0.4, 1.0, n)


def run(effects: dict, u: np.ndarray, base: PlantParams = BASE, dt: float = DT):
    model = build_model(base.with_changes(effects=effects))
    return model.simulate(u, dt, PlantState())


def euler_reference(u, dt, p: PlantParams, friction, force=lambda x: 0.0, static=None, sub=400):
    """Explicit Euler with tiny steps and a zero-crossing clamp: slow, simple, independent."""
    h = dt / sub
    v = x = 0.0
    static = static or (p.breakaway_pos, p.breakaway_neg)
    out = []
    for uk in u:
        out.append(v)
        for _ in range(sub):
            f = uk - force(x)
            if v == 0.0:
                if -static[1] <= f <= static[0]:
                    continue
                fr = friction(0.0, 1 if f > 0 else -1)
            else:
                fr = friction(abs(v), 1 if v > 0 else -1)
            vn = v + h * (f - fr - p.B * v) / p.M
            if v != 0.0 and (vn > 0) != (v > 0):
                vn = 0.0
            x += h * vn
            v = vn
    return np.array(out)


@pytest.mark.parametrize(
    "effects",
    [
        {"offset": {"offset": 0.0}},
        {"viscous_asymmetry": {"dB": 0.0}},
        {"time_delay": {"delay": 0.0}},
        {"saturation": {"limit": 100.0}},
        {"cogging": {"amp": 0.0, "period": 0.1, "phase": 0.0}},
    ],
)
def test_an_effect_at_zero_strength_is_the_exact_base_plant(effects):
    u = command()
    v0, x0, _ = simulate_coulomb(u, DT, BASE)
    v, x, _ = run(effects, u)
    assert_allclose(v, v0, atol=1e-12)
    assert_allclose(x, x0, atol=1e-12)


@pytest.mark.parametrize(
    "effects, transform",
    [
        ({"offset": {"offset": 0.3}}, lambda u: u + 0.3),
        ({"saturation": {"limit": 1.5}}, lambda u: np.clip(u, -1.5, 1.5)),
        ({"deadzone": {"width": 0.7}}, lambda u: np.sign(u) * np.maximum(np.abs(u) - 0.7, 0)),
        ({"quantization": {"step": 0.4}}, lambda u: 0.4 * np.round(u / 0.4)),
        ({"time_delay": {"delay": 3 * DT}}, lambda u: np.concatenate([np.zeros(3), u[:-3]])),
    ],
)
def test_command_effects_equal_the_exact_plant_on_the_transformed_command(effects, transform):
    u = command()
    v0, x0, _ = simulate_coulomb(transform(u), DT, BASE)
    v, x, _ = run(effects, u)
    assert_allclose(v, v0, atol=1e-12)
    assert_allclose(x, x0, atol=1e-12)


def test_fractional_delay_is_exact_under_zero_order_hold():
    u = command()
    v, _, _ = run({"time_delay": {"delay": 2.5 * DT}}, u)
    fine = np.concatenate([np.zeros(5), np.repeat(u, 2)[:-5]])  # half-sample grid, shifted 5
    v_ref, _, _ = simulate_coulomb(fine, DT / 2, BASE)
    assert_allclose(v, v_ref[::2], atol=1e-12)


def test_viscous_asymmetry_sets_each_direction_steady_speed():
    u = np.concatenate([np.full(2000, 2.0), np.full(2000, -2.0)])
    v, _, _ = run({"viscous_asymmetry": {"dB": 0.25}}, u)
    assert v[1999] == pytest.approx((2.0 - 0.5) / 1.25, rel=1e-6)
    assert v[-1] == pytest.approx(-(2.0 - 0.4) / 0.75, rel=1e-6)


def test_stribeck_matches_a_fine_step_reference():
    fs, vs = 0.9, 0.08
    u = command(n=800)

    def friction(speed, d):
        fc = BASE.coulomb_pos if d > 0 else BASE.coulomb_neg
        return d * (fc + (fs - fc) * math.exp(-((speed / vs) ** 2)))

    v, _, _ = run({"stribeck": {"fs": fs, "vs": vs}}, u)
    v_ref = euler_reference(u, DT, BASE, friction, static=(fs, fs))
    assert np.sqrt(np.mean((v - v_ref) ** 2)) < 0.01 * np.std(v_ref)


def test_cogging_matches_a_fine_step_reference():
    amp, period, phase = 0.3, 0.05, 0.4
    u = command(n=800)

    def friction(speed, d):
        return BASE.coulomb_pos if d > 0 else -BASE.coulomb_neg

    force = lambda x: amp * math.sin(2 * math.pi * x / period + phase)  # noqa: E731
    v, _, _ = run({"cogging": {"amp": amp, "period": period, "phase": phase}}, u)
    v_ref = euler_reference(u, DT, BASE, friction, force)
    assert np.sqrt(np.mean((v - v_ref) ** 2)) < 0.01 * np.std(v_ref)


@pytest.mark.parametrize(
    "effects, u_rest",
    [
        ({"stribeck": {"fs": 0.9, "vs": 0.05}}, 0.85),  # below the static level, above Coulomb
        ({"cogging": {"amp": 0.2, "period": 0.1, "phase": 0.0}}, 0.45),  # F_cog(0) = 0
        ({"backlash": {"gap": 0.02, "ratio": 0.5}}, 0.45),
        ({"resonance": {"wn": 300.0, "zeta": 0.05, "ratio": 0.5}}, 0.45),
        ({"deadzone": {"width": 1.0}}, 1.4),  # 0.4 of force left, below breakaway
    ],
)
def test_a_body_at_rest_stays_at_rest_below_breakaway(effects, u_rest):
    v, x, st = run(effects, np.full(500, u_rest))
    assert np.all(v == 0.0) and np.all(x == 0.0) and st.v == 0.0


@pytest.mark.parametrize(
    "effects",
    [
        {"stribeck": {"fs": 0.9, "vs": 0.05}},
        {"cogging": {"amp": 0.2, "period": 0.1, "phase": 0.0}},
        {"backlash": {"gap": 0.02, "ratio": 0.5}},
        {"resonance": {"wn": 300.0, "zeta": 0.3, "ratio": 0.5}},
    ],
)
def test_no_chatter_once_stopped(effects):
    u = np.concatenate([np.full(300, 2.0), np.full(1500, 0.2)])  # 0.2 holds inside breakaway
    v, _, _ = run(effects, u)
    tail = v[-500:]
    assert np.all(np.abs(tail) < 1e-9)  # a load on a spring only decays towards rest
    assert np.all(np.diff(np.sign(tail)) == 0)


def test_resonance_without_friction_is_the_rigid_body_times_the_series_mode():
    from scipy.signal import lsim

    wn, zeta, r = 150.0, 0.05, 0.5
    base = PlantParams(M=0.1, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0)
    rng = np.random.default_rng(7)
    u = np.repeat(rng.normal(0, 2.0, 60), 25)
    v, _, _ = run({"resonance": {"wn": wn, "zeta": zeta, "ratio": r}}, u, base)
    # (1/(M s + B)) * (2 zeta wn s + wn^2) / (s^2 + (2 zeta wn + B/M) s + wn^2), ZOH input.
    num = [2 * zeta * wn, wn**2]
    den = np.polymul([base.M, base.B], [1.0, 2 * zeta * wn + base.B / base.M, wn**2])
    t_fine = np.arange(u.size * 20) * DT / 20
    _, y, _ = lsim((num, den), np.repeat(u, 20), t_fine)
    assert_allclose(v, y[::20], atol=2e-3 * np.max(np.abs(y)))


def test_backlash_impact_conserves_momentum():
    r, gap = 0.4, 0.05
    u = np.full(1000, 2.0)
    v, x, _ = run({"backlash": {"gap": gap, "ratio": r}}, u, dt=1e-4)
    # Alone, the motor (mass (1-r) M) accelerates faster than the joint body would.
    free = (2.0 - BASE.coulomb_pos) / ((1 - r) * BASE.M)
    assert (v[20] - v[10]) / (10 * 1e-4) == pytest.approx(free, rel=0.02)
    jump = int(np.argmax(np.diff(v) < 0))  # the impact: the motor slows down
    assert x[jump] == pytest.approx(gap / 2, abs=2e-3)
    assert v[jump + 1] == pytest.approx((1 - r) * v[jump], rel=0.05)


@pytest.mark.parametrize(
    "effects",
    [
        {"time_delay": {"delay": 2.5 * DT}, "saturation": {"limit": 1.8}},
        {"stribeck": {"fs": 0.9, "vs": 0.05}, "viscous_asymmetry": {"dB": 0.2}},
        {"resonance": {"wn": 200.0, "zeta": 0.1, "ratio": 0.5}},
        {
            "backlash": {"gap": 0.02, "ratio": 0.5},
            "cogging": {"amp": 0.1, "period": 0.1, "phase": 0},
        },
    ],
)
def test_sample_by_sample_equals_one_block(effects):
    """What the simulated drive does (one sample per call) equals one long call."""
    u = command(n=600)
    p = BASE.with_changes(effects=effects)
    block = Plant(p)
    v_block, x_block = block.step_block(u, DT)
    single = Plant(p)
    pairs = [single.step_block(u[k : k + 1], DT) for k in range(u.size)]
    assert_allclose(np.concatenate([a for a, _ in pairs]), v_block, atol=1e-12)
    assert_allclose(np.concatenate([b for _, b in pairs]), x_block, atol=1e-12)


def _posfric(values, x_from=-0.2, x_to=0.6) -> dict:
    out = {"x_from": x_from, "x_to": x_to, "knots": float(len(values))}
    out.update({f"f{i}": float(v) for i, v in enumerate(values)})
    return {"position_friction": out}


def test_position_friction_at_zero_is_the_exact_base_plant():
    u = command()
    v0, x0, _ = simulate_coulomb(u, DT, BASE)
    v, x, _ = run(_posfric([0.0, 0.0, 0.0, 0.0]), u)
    assert_allclose(v, v0, atol=1e-12)
    assert_allclose(x, x0, atol=1e-12)


def test_a_flat_position_friction_is_the_exact_plant_with_both_levels_raised():
    u = command()
    raised = BASE.with_changes(
        coulomb_pos=BASE.coulomb_pos + 0.2, coulomb_neg=BASE.coulomb_neg + 0.2
    )
    v0, x0, _ = simulate_coulomb(u, DT, raised)
    v, x, _ = run(_posfric([0.2, 0.2, 0.2]), u)
    assert_allclose(v, v0, atol=1e-9)
    assert_allclose(x, x0, atol=1e-9)


def test_position_friction_matches_a_fine_step_reference_with_scipy_s_spline():
    """Against explicit Euler with tiny steps and the natural cubic spline built by another scipy
    routine (B-spline interpolation), held at its end values outside the knots."""
    from scipy.interpolate import make_interp_spline

    u, sub = command(n=800), 200
    _, x_base, _ = simulate_coulomb(u, DT, BASE)
    values, x0, x1 = [0.0, 0.35, -0.15, 0.5, 0.2], float(x_base.min()), float(x_base.max())
    spline = make_interp_spline(np.linspace(x0, x1, 5), values, k=3, bc_type="natural")

    def extra(x):
        return float(spline(min(max(x, x0), x1)))

    h = DT / sub
    v = x = 0.0
    out = []
    for uk in u:
        out.append(v)
        for _ in range(sub):
            g = extra(x)
            fcp, fcn = BASE.coulomb_pos + g, BASE.coulomb_neg + g
            if v == 0.0 and -fcn <= uk <= fcp:
                continue
            d = (1 if uk > 0 else -1) if v == 0.0 else (1 if v > 0 else -1)
            vn = v + h * (uk - (fcp if d > 0 else -fcn) - BASE.B * v) / BASE.M
            if v != 0.0 and (vn > 0) != (v > 0):
                vn = 0.0
            x += h * vn
            v = vn
    v_ref = np.array(out)
    v_sim, x_sim, _ = run(_posfric(values, x0, x1), u)
    assert np.ptp(x_sim) > 0.5 * (x1 - x0)  # the axis crosses most of the knots
    assert np.sqrt(np.mean((v_sim - v_ref) ** 2)) < 0.01 * np.std(v_ref)


def test_position_friction_below_zero_is_refused_when_the_model_is_built():
    from servobench.errors import UsageError

    with pytest.raises(UsageError, match="below zero along the travel"):
        build_model(BASE.with_changes(effects=_posfric([0.0, -0.6, 0.0])))
