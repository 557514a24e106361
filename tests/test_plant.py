"""The exact ZOH stick-slip plant against analytic solutions and a fine-step reference."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.errors import UsageError
from servobench.sim_backend.physics.plant import (
    Plant,
    PlantParams,
    PlantState,
    simulate,
    simulate_coulomb,
)

DT = 1e-3


def reference(u: np.ndarray, dt: float, p: PlantParams, sub: int = 2000) -> np.ndarray:
    """Explicit Euler with tiny steps and a zero-crossing clamp: slow, simple, independent."""
    h = dt / sub
    v = 0.0
    out = []
    for uk in u:
        out.append(v)
        for _ in range(sub):
            if v == 0.0:
                if uk > p.breakaway_pos:
                    f = p.coulomb_pos
                elif uk < -p.breakaway_neg:
                    f = -p.coulomb_neg
                else:
                    continue
            else:
                f = p.coulomb_pos if v > 0 else -p.coulomb_neg
            vn = v + h * (uk - f - p.B * v) / p.M
            if v != 0.0 and (vn > 0) != (v > 0):
                vn = 0.0
            v = vn
    return np.array(out)


def test_step_response_matches_the_analytic_solution():
    p = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
    u = np.full(500, 3.0)
    v, x, _ = simulate_coulomb(u, DT, p)
    t = np.arange(500) * DT
    tau = p.M / p.B
    assert_allclose(v, 2.5 * (1 - np.exp(-t / tau)), rtol=1e-12, atol=1e-14)
    assert_allclose(x, 2.5 * (t - tau * (1 - np.exp(-t / tau))), rtol=1e-10, atol=1e-14)


def test_negative_direction_uses_its_own_coulomb_level():
    p = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
    v, _, _ = simulate_coulomb(np.full(3000, -3.0), DT, p)
    assert v[-1] == pytest.approx(-(3.0 - 0.4), rel=1e-9)


def test_body_at_rest_stays_at_rest_below_breakaway():
    p = PlantParams(coulomb_pos=0.5, coulomb_neg=0.4, brk_pos=0.8, brk_neg=0.7)
    u = np.concatenate([np.full(100, 0.79), np.full(100, -0.69), np.full(100, 0.0)])
    v, x, st = simulate_coulomb(u, DT, p)
    assert np.all(v == 0.0) and np.all(x == 0.0) and st.v == 0.0


def test_breakaway_then_coulomb_keeps_moving():
    p = PlantParams(coulomb_pos=0.5, coulomb_neg=0.4, brk_pos=0.8, brk_neg=0.7)
    u = np.concatenate([np.full(50, 0.9), np.full(2000, 0.6)])
    v, _, _ = simulate_coulomb(u, DT, p)
    assert v[-1] == pytest.approx(0.1, rel=1e-6)  # (0.6 - 0.5) / B: still sliding


def test_no_chatter_after_stopping():
    p = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
    u = np.concatenate([np.full(300, 2.0), np.full(700, 0.3)])  # 0.3 is inside [-0.4, 0.5]
    v, _, _ = simulate_coulomb(u, DT, p)
    stopped = int(np.flatnonzero(v[300:] == 0.0)[0]) + 300
    assert np.all(v[stopped:] == 0.0)
    assert np.all(v[:stopped] >= 0.0)


@pytest.mark.parametrize("amplitude", [0.7, 1.0, 5.0])
def test_stick_slip_matches_a_fine_step_reference(amplitude):
    p = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4, brk_pos=0.6, brk_neg=0.45)
    rng = np.random.default_rng(3)
    u = amplitude * np.repeat(rng.choice([-1.0, 1.0], 20), 10)
    v, _, _ = simulate_coulomb(u, DT, p)
    v_ref = reference(u, DT, p)
    assert_allclose(v, v_ref, atol=2e-3 * max(1.0, np.abs(v_ref).max()))


def test_state_is_carried_across_blocks():
    p = PlantParams()
    u = np.sign(np.sin(np.arange(1000) * 0.02)) * 2.0
    v_all, x_all, _ = simulate_coulomb(u, DT, p)
    v1, x1, st = simulate_coulomb(u[:437], DT, p)
    v2, x2, _ = simulate_coulomb(u[437:], DT, p, st)
    assert_allclose(np.concatenate([v1, v2]), v_all, rtol=0, atol=1e-15)
    assert_allclose(np.concatenate([x1, x2]), x_all, rtol=0, atol=1e-15)


def test_sensor_noise_is_seeded_and_quantization_applies():
    p = PlantParams(noise=0.01, res_x=1e-3, seed=7)
    u = np.full(200, 2.0)
    v1, x1 = simulate(u, 1000.0, p)
    v2, x2 = simulate(u, 1000.0, p)
    assert_allclose(v1, v2)
    assert np.allclose(x1 / 1e-3, np.round(x1 / 1e-3))
    true_v, _, _ = simulate_coulomb(u, 1e-3, p)
    assert 0.005 < np.std(v1 - true_v) < 0.02


def test_plant_reset_and_state():
    plant = Plant(PlantParams())
    plant.step_block(np.full(100, 2.0), DT)
    assert plant.state.v > 0
    plant.reset()
    assert plant.state == PlantState()


@pytest.mark.parametrize(
    "changes",
    [{"M": 0.0}, {"B": -1.0}, {"coulomb_pos": -0.1}, {"M": math.nan}, {"brk_pos": 0.1}, {"noise": -1}],
)
def test_bad_parameters_are_refused(changes):
    with pytest.raises(UsageError):
        PlantParams(**changes)


def test_frictionless_plant_is_the_linear_block():
    p = PlantParams(M=0.1, B=1.0, coulomb_pos=0.0, coulomb_neg=0.0)
    u = np.concatenate([np.full(300, 2.0), np.full(300, -1.0), np.full(300, 0.5)])
    v, _, _ = simulate_coulomb(u, DT, p)
    a = math.exp(-DT * p.B / p.M)
    expected = np.zeros_like(u)
    for k in range(1, len(u)):
        expected[k] = a * expected[k - 1] + (1 - a) * u[k - 1] / p.B
    assert_allclose(v, expected, rtol=1e-10, atol=1e-13)
