"""SIDBE as published: differential FRF, parametric fit, friction."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.bench.identify.auto import identify
from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.frequency import (
    FrequencyResponse,
    differential_frf,
    fit_linear_block,
    model_frf,
)
from servobench.bench.identify.sidbe import identify_sidbe
from servobench.bench.model.servo import Resonance, ServoModel
from servobench.bench.procedure.excitation import design_excitation, make_design
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.plant import PlantParams

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def test_sidbe_as_published_at_60():
    r = identify(simulate_experiment(TRUE, make_design(60.0)), "sidbe")
    assert r.method == "sidbe" and r.estimator == "frf"
    assert_allclose([r.model.pole, r.model.dc_gain], [-10.0, 1.0], rtol=0.03)
    assert_allclose([r.model.coulomb_pos, r.model.coulomb_neg], [0.5, 0.4], rtol=0.05)
    assert r.fit_percent > 99.0
    assert r.frf is not None and r.frf.periods_averaged == 3
    # no action delay in the plant: what friction leaves in the phase is far below a sample
    assert 0.0 <= r.model.delay_s < 1e-3 / 1000.0 and "delay_s" in r.std


def test_sidbe_is_biased_at_the_friction_level_and_joint_is_not():
    log = simulate_experiment(TRUE, make_design(1.0))
    sidbe = identify(log, "sidbe").model
    joint = identify(log, "joint").model
    assert abs(sidbe.pole / -10.0 - 1) > 0.1  # the differential pair leaves friction in
    assert abs(joint.pole / -10.0 - 1) < 1e-3


def test_linear_plant_frf_is_exact():
    """Without friction the differential FRF equals the sampled 1/(Ms+B) at every line."""
    d = make_design(1.0)
    log = simulate_experiment(TRUE.with_changes(coulomb_pos=0.0, coulomb_neg=0.0), d)
    data = prepare(log)
    r1, r2 = data.run(1), data.run(2)
    frf = differential_frf(r1.u, r1.v, r2.u, r2.v, d)
    expected = model_frf(ServoModel(0.1, 1.0, 0.0, 0.0), frf.f_hz, frf.dt_s)
    assert_allclose(frf.G, expected, rtol=1e-6)


def _linear_frf(model: ServoModel, design) -> FrequencyResponse:
    """Periodic steady-state response of a linear (friction-free) model, via the FFT."""
    exc = design_excitation(design)
    n = design.samples_per_period
    f = design.lines * design.fs_hz / n
    g = model_frf(model, f, 1.0 / design.fs_hz)
    U1 = np.fft.rfft(exc.u1[:n])[design.lines] / n
    U2 = design.ratio * U1
    return FrequencyResponse(f, g, U1, U2, g * U1, g * U2, 1.0 / design.fs_hz, 3)


def test_resonance_fit_recovers_the_series_mode():
    true = ServoModel(0.1, 1.0, 0.0, 0.0, Resonance(2 * math.pi * 25.0, 0.08))
    design = make_design(
        1.0, freqs_hz=tuple(np.unique(np.round(np.geomspace(0.25, 120, 30) * 4)) / 4)
    )
    fit = fit_linear_block(_linear_frf(true, design), resonance=True)
    assert_allclose(
        [fit.M, fit.B, fit.wn_rad_s, fit.zeta], [0.1, 1.0, 2 * math.pi * 25.0, 0.08], rtol=1e-4
    )
    assert fit.delay_s == 0.0 and fit.delay_separable


def test_sidbe_needs_the_pair_and_the_design():
    log = simulate_experiment(TRUE, make_design(5.0))
    single = type(log)(log.runs[:1], log.metadata, log.fs_hz)
    with pytest.raises(IdentificationError, match="u1/u2"):
        identify_sidbe(prepare(single))
    bare = type(log)(log.runs, {"fs": "1000"}, log.fs_hz)
    with pytest.raises(IdentificationError, match="periodic excitation"):
        identify(bare, "sidbe")


def test_position_only_sidbe_fits_the_position_frf_exactly():
    linear = TRUE.with_changes(coulomb_pos=0.0, coulomb_neg=0.0)
    log = simulate_experiment(
        linear, make_design(5.0, period_s=2.0, periods=3), with_velocity=False
    )
    r = identify(log, "sidbe")
    assert_allclose([r.model.M, r.model.B], [0.1, 1.0], rtol=1e-6)
    assert r.model.delay_s == 0.0  # delay-free data: the fitted delay ends on its bound
    expected = model_frf(r.model, r.frf.f_hz, r.frf.dt_s)
    assert_allclose(r.frf.G, expected, rtol=1e-5)  # the plotted FRF is velocity over command


def test_resonance_option_without_a_mode_falls_back_and_says_so():
    log = simulate_experiment(TRUE, make_design(5.0))
    r = identify(log, "sidbe", resonance=True)
    assert r.model.resonance is None
    assert any("no resonance" in n for n in r.notes)
