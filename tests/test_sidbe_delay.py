"""SIDBE identifies the drive's action delay jointly with M and B (issue 28, item 2).

``u[k]`` logged at ``t_k`` acts over ``[t_k + d, t_{k+1} + d)``. The logs here
are made independently of the estimator: the delayed command is laid on the
grid of the sample instants and the switch instants ``t_k + d``, integrated
exactly (stick-slip, one step per grid interval), and the sample rows are
taken back out.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.frequency import (
    FrequencyResponse,
    _delayed_hold,
    differential_frf,
    fit_linear_block,
    model_frf,
    zoh_first_order,
    zoh_position,
)
from servobench.bench.identify.sidbe import _friction_sampled, identify_sidbe
from servobench.bench.identify.simulation import simulate_variable_dt
from servobench.bench.log.io import ExperimentLog, RunData
from servobench.bench.model.servo import Resonance, ServoModel
from servobench.bench.procedure.excitation import design_excitation, make_design
from servobench.sim_backend.physics.coulomb import simulate_coulomb_steps
from servobench.sim_backend.physics.plant import PlantParams

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)
LINEAR = TRUE.with_changes(coulomb_pos=0.0, coulomb_neg=0.0)
DELAYS = (0.3, 1.0, 1.7)  # samples


def _delayed_grid(u: np.ndarray, dt_s: float, q: float):
    """``(u_m, dt_m, rows)``: over ``[t_k, t_k + f dt)`` ``u[k-m-1]`` acts, then ``u[k-m]``
    (0 before ``u[0]``); ``rows`` are the sample instants on the grid."""
    m = int(math.floor(q))
    f = q - m
    n = len(u)
    padded = np.concatenate((np.zeros(m + 1), u))
    now, before = padded[1 : n + 1], padded[:n]
    if f == 0:
        return now, np.full(n - 1, dt_s), np.arange(n)
    u_m = np.empty(2 * n)
    u_m[0::2], u_m[1::2] = before, now
    dt_m = np.empty(2 * n - 1)
    dt_m[0::2], dt_m[1::2] = f * dt_s, (1 - f) * dt_s
    return u_m, dt_m, 2 * np.arange(n)


def _delayed_log(params, design, q, noise=0.0, seed=0, position=False) -> ExperimentLog:
    """The two SIDBE runs of ``design`` on ``params`` with an action delay of ``q`` samples."""
    rng = np.random.default_rng(seed)
    dt = 1.0 / design.fs_hz
    runs = []
    for number, u in design_excitation(design).runs():
        u_m, dt_m, rows = _delayed_grid(u, dt, q)
        if position:
            v, x, _ = simulate_coulomb_steps(u_m, dt_m, params)
            v, x = None, x[rows]
        else:
            v, x = simulate_variable_dt(u_m, dt_m, params)[rows], None
            v = v + noise * rng.standard_normal(v.shape)
        runs.append(RunData(number, np.arange(len(u)) * dt, u.copy(), v, x))
    meta = {k: _text(val) for k, val in design.metadata().items()}
    meta["loop"] = "open"
    return ExperimentLog(tuple(runs), meta, design.fs_hz, True, "synthetic")


def _text(value: object) -> str:
    if isinstance(value, (list, tuple)):
        return ",".join(format(float(e), ".17g") for e in value)
    return format(value, ".17g") if isinstance(value, float) else str(value)


def _design(amplitude: float, position: bool):
    return make_design(amplitude, period_s=2.0, periods=3) if position else make_design(amplitude)


def _exact_frf(model: ServoModel, design) -> FrequencyResponse:
    """The differential FRF of a linear model, exactly (its sampled response at the lines)."""
    n = design.samples_per_period
    f = design.lines * design.fs_hz / n
    g = model_frf(model, f, 1.0 / design.fs_hz)
    U1 = np.fft.rfft(design_excitation(design).u1[:n])[design.lines] / n
    U2 = design.ratio * U1
    return FrequencyResponse(f, g, U1, U2, g * U1, g * U2, 1.0 / design.fs_hz, 3)


@pytest.mark.parametrize("q", (*DELAYS, 0.999999, 2.0))
def test_delayed_hold_closed_forms_agree_with_the_state_space_hold(q):
    M, B, dt = 0.1, 1.0, 1e-3
    z = np.exp(2j * np.pi * np.array([0.5, 3.0, 40.0, 310.0]) * dt)
    velocity = _delayed_hold(np.array([[-B / M]]), np.array([[1 / M]]), np.eye(1), z, dt, q * dt)
    assert_allclose(zoh_first_order(M, B, z, dt, q * dt), velocity, rtol=1e-10)
    A = np.array([[0.0, 1.0], [0.0, -B / M]])
    position = _delayed_hold(A, np.array([[0.0], [1 / M]]), np.array([[1.0, 0.0]]), z, dt, q * dt)
    assert_allclose(zoh_position(M, B, z, dt, q * dt), position, rtol=1e-9)
    # continuous in the delay: just below a whole sample is that whole sample
    whole = math.ceil(q)
    if whole - q < 1e-5:
        assert_allclose(zoh_first_order(M, B, z, dt, q * dt), zoh_first_order(M, B, z, dt, whole * dt),
                        rtol=1e-4)  # fmt: skip
    s = 2j * np.pi * 3.0
    continuous = model_frf(ServoModel(M, B, 0.0, 0.0, delay_s=q * dt), [3.0])
    assert_allclose(continuous, np.exp(-s * q * dt) / (M * s + B), rtol=1e-12)


@pytest.mark.parametrize("position", (False, True), ids=("velocity", "position"))
@pytest.mark.parametrize("q", DELAYS)
def test_noise_free_linear_logs_give_the_delay_and_the_plant_exactly(q, position):
    r = identify_sidbe(prepare(_delayed_log(LINEAR, _design(1.0, position), q, position=position)))
    m = r.model
    assert_allclose([m.M, m.B], [0.1, 1.0], rtol=1e-6)
    assert abs(m.delay_s * 1e3 - q) < 1e-3  # samples
    assert r.std["delay_s"] < 1e-3 * 1e-3
    assert any("drive action delay" in n and "FRF phase" in n for n in r.notes)
    assert_allclose(r.frf.G, model_frf(m, r.frf.f_hz, r.frf.dt_s), rtol=1e-5)


@pytest.mark.parametrize("position", (False, True), ids=("velocity", "position"))
def test_delay_free_logs_give_no_delay_and_the_delay_free_fit(position):
    log = _delayed_log(LINEAR, _design(1.0, position), 0.0, position=position)
    r = identify_sidbe(prepare(log))
    assert r.model.delay_s == 0.0
    assert not any("delay" in n for n in r.notes)
    assert_allclose([r.model.M, r.model.B], [0.1, 1.0], rtol=1e-6)
    # velocity: the joint fit ends on its bound and returns the delay-free fit unchanged
    data = prepare(_delayed_log(LINEAR, make_design(1.0), 0.0))
    r1, r2 = data.run(1), data.run(2)
    frf = differential_frf(r1.u, r1.v, r2.u, r2.v, data.design)
    joint, free = fit_linear_block(frf), fit_linear_block(frf, delay=False)
    assert (joint.M, joint.B, joint.delay_s) == (free.M, free.B, 0.0)
    assert math.isnan(free.std_delay_s) and joint.delay_separable


@pytest.mark.parametrize("q", DELAYS)
def test_friction_well_above_its_level_with_the_exact_delayed_friction_step(q):
    data = prepare(_delayed_log(TRUE, make_design(60.0), q))
    m = identify_sidbe(data).model
    assert abs(m.delay_s * 1e3 - q) < 1e-3
    assert_allclose([m.M, m.B], [0.1, 1.0], rtol=1e-4)
    assert_allclose([m.coulomb_pos, m.coulomb_neg], [0.5, 0.4], rtol=1e-3)
    # the held command in place of the delayed one would misread the friction
    plain = _friction_sampled(data, m.M, m.B, 0.0)
    assert abs(plain[0] - 0.5) > 0.1


@pytest.mark.parametrize("position", (False, True), ids=("velocity", "position"))
@pytest.mark.parametrize("q", DELAYS)
def test_at_three_times_friction_the_delay_adds_nothing_to_sidbe_bias(q, position):
    """Near the friction level the differential pair leaves friction in (a bias of its
    own, delay or not): the delayed log's estimate is the delay-free one's, shifted by q."""
    design = _design(1.5, position)
    delayed = identify_sidbe(prepare(_delayed_log(TRUE, design, q, position=position))).model
    free = identify_sidbe(prepare(_delayed_log(TRUE, design, 0.0, position=position))).model
    assert abs((delayed.delay_s - free.delay_s) * 1e3 - q) < 0.05
    assert_allclose([delayed.M, delayed.B], [free.M, free.B], rtol=3e-3)
    assert_allclose([delayed.coulomb_pos, delayed.coulomb_neg],
                    [free.coulomb_pos, free.coulomb_neg], rtol=3e-3)  # fmt: skip


@pytest.mark.parametrize("q", (0.3, 1.7))
def test_noisy_delay_is_within_three_sigma(q):
    for seed in range(4):
        r = identify_sidbe(prepare(_delayed_log(LINEAR, make_design(1.0), q, 0.002, seed)))
        sigma = r.std["delay_s"]
        assert 0 < sigma < 0.2e-3
        assert abs(r.model.delay_s - q * 1e-3) < 3 * sigma
        assert abs(r.model.M - 0.1) < 3 * r.std["M"]


def test_a_delay_the_band_cannot_tell_from_the_plant_is_flagged():
    design = make_design(1.0)  # lines up to 40 Hz
    slow = fit_linear_block(_exact_frf(ServoModel(0.1, 1.0, 0, 0, delay_s=1e-3), design))
    assert slow.delay_separable and slow.delay_correlation < 0.5
    # a 0.3 ms time constant (530 Hz) and a 1 ms delay look alike far below the corner
    fast = fit_linear_block(_exact_frf(ServoModel(3e-4, 1.0, 0, 0, delay_s=1e-3), design))
    assert not fast.delay_separable and fast.delay_correlation > 0.99


def test_resonance_and_delay_are_fitted_together():
    true = ServoModel(0.1, 1.0, 0.0, 0.0, Resonance(2 * math.pi * 25.0, 0.08), delay_s=1.7e-3)
    design = make_design(
        1.0, freqs_hz=tuple(np.unique(np.round(np.geomspace(0.25, 120, 30) * 4)) / 4)
    )
    fit = fit_linear_block(_exact_frf(true, design), resonance=True)
    assert_allclose(
        [fit.M, fit.B, fit.wn_rad_s, fit.zeta], [0.1, 1.0, 2 * math.pi * 25.0, 0.08], rtol=1e-4
    )
    assert abs(fit.delay_s * 1e3 - 1.7) < 1e-3
