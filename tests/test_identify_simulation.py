"""The simulation helpers agree with the exact plant integrator."""

import numpy as np
from numpy.testing import assert_allclose

from servobench.bench.identify.simulation import (
    simulate_run,
    simulate_steady_period,
    simulate_variable_dt,
)
from servobench.bench.model.servo import ServoModel
from servobench.bench.procedure.excitation import design_excitation, make_design
from servobench.sim_backend.physics.plant import PlantState, simulate_coulomb

MODEL = ServoModel(0.1, 1.0, 0.5, 0.4)


def test_variable_dt_integrator_matches_plant_for_constant_and_jittered_dt():
    u = design_excitation(make_design(1.0, periods=2)).u1
    params = MODEL.to_plant_params()
    ref, _, _ = simulate_coulomb(u, 1e-3, params)
    assert_allclose(simulate_variable_dt(u, np.full(len(u) - 1, 1e-3), params), ref, atol=1e-12)
    rng = np.random.default_rng(0)
    dts = 1e-3 * (1 + 0.3 * rng.uniform(-1, 1, 2000))
    u2 = u[:2001]
    chained = [0.0]
    state = PlantState()
    for k in range(2000):
        _, _, state = simulate_coulomb(u2[k : k + 1], dts[k], params, state)
        chained.append(state.v)
    assert_allclose(simulate_variable_dt(u2, dts, params), chained, atol=1e-12)


def test_tiled_periodic_run_equals_full_simulation():
    d = make_design(1.0, periods=12, period_s=1.0)
    u = design_excitation(d).u1
    full, _, _ = simulate_coulomb(u, 1e-3, MODEL.to_plant_params())
    assert_allclose(simulate_run(MODEL, u, 1e-3, 0.0, d.samples_per_period), full, atol=1e-8)
    steady = simulate_steady_period(MODEL, u[: d.samples_per_period], 1e-3)
    assert_allclose(steady, full[-d.samples_per_period :], atol=1e-6)
