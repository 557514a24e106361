"""PI design and friction feed-forward: margins, closed-loop behaviour, the compensation benefit."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.bench.commission.closedloop import (
    check_compensation,
    reference_amplitude,
    simulate_loop,
)
from servobench.bench.commission.config import CompensationSettings
from servobench.bench.commission.design import (
    FrictionFeedForward,
    design_pi,
    friction_feed_forward,
    loop_response,
    margins,
)
from servobench.errors import UsageError
from servobench.sim_backend.physics.plant import PlantParams

PLANTS = [(0.1, 1.0), (2.0, 0.5), (0.001, 1.0), (100.0, 0.01)]


@pytest.mark.parametrize(("M", "B"), PLANTS)
def test_design_meets_the_phase_and_gain_margin(M, B):
    pi = design_pi(M, B, 1000.0, phase_margin_deg=60.0, delay_cycles=1.0)
    _, pm, gm = margins(M, B, pi.kp, pi.ki, pi.sample_time_s, pi.delay_cycles)
    assert pm == pytest.approx(pi.phase_margin_deg)
    assert pm >= 59.9 and gm >= 6.0
    assert pi.kp > 0 and pi.ki > 0 and pi.ti_s == pytest.approx(pi.kp / pi.ki)
    # |L| = 1 at the reported crossover
    L = loop_response(M, B, pi.kp, pi.ki, pi.sample_time_s, 1.0, np.array([2 * math.pi * pi.crossover_hz]))
    assert abs(L[0]) == pytest.approx(1.0, rel=0.01)


def test_pi_zero_ratio_design_matches_the_continuous_approximation():
    # slow plant pole: Ti = 4/wc and PM ~ 180 - 90 - atan(1/4) - atan(wc M/B) - wc (d + 1/2) T
    M, B, fs = 0.1, 1.0, 1000.0
    pi = design_pi(M, B, fs, phase_margin_deg=60.0)
    wc = 2 * math.pi * pi.crossover_hz
    assert pi.ti_s == pytest.approx(4.0 / wc, rel=0.02)
    approx = 180 - math.degrees(math.atan(0.25) + math.atan(wc * M / B) + wc * 1.5 / fs)
    assert approx == pytest.approx(60.0, abs=3.0)


def test_more_delay_or_more_margin_means_a_slower_loop():
    base = design_pi(0.1, 1.0, 1000.0)
    assert design_pi(0.1, 1.0, 1000.0, delay_cycles=3).crossover_hz < base.crossover_hz
    assert design_pi(0.1, 1.0, 1000.0, phase_margin_deg=70).crossover_hz < base.crossover_hz
    capped = design_pi(0.1, 1.0, 1000.0, max_bandwidth_hz=5.0)
    assert capped.crossover_hz <= 5.0 * 1.01 and capped.limited_by == "max_bandwidth_hz"
    assert capped.phase_margin_deg > 60.0


def test_design_rejects_bad_input():
    with pytest.raises(UsageError):
        design_pi(-1.0, 1.0, 1000.0)
    with pytest.raises(UsageError, match="no PI reaches"):
        design_pi(0.1, 1.0, 1000.0, min_gain_margin_db=80.0)


@pytest.mark.parametrize(("M", "B"), PLANTS[:3])
def test_designed_loop_tracks_a_step_without_friction(M, B):
    pi = design_pi(M, B, 1000.0)
    r = np.full(1500, 1.0)
    run = simulate_loop(PlantParams(M=M, B=B, coulomb_pos=0.0, coulomb_neg=0.0), pi, r, max_u=1e6)
    assert run.v[0] == 0.0 and run.u[0] == 0.0  # one cycle of delay
    overshoot = run.v.max() - 1.0
    assert abs(run.v[-100:] - 1.0).max() < 1e-3  # integral action: no steady-state error
    assert overshoot < 0.3  # 60 deg of phase margin: modest overshoot


def test_feed_forward_values_and_band():
    ff = FrictionFeedForward(coulomb_pos=0.5, coulomb_neg=0.4, viscous=2.0)
    assert_allclose(ff(np.array([1.0, -1.0, 0.0])), [2.5, -2.4, 0.0])
    banded = FrictionFeedForward(0.5, 0.4, 0.0, sign_band=0.1)
    assert_allclose(banded(np.array([0.05, -0.05, 0.2])), [0.25, -0.2, 0.5])
    assert friction_feed_forward(1.0, -0.1, 0.3).coulomb_pos == 0.0
    with pytest.raises(UsageError):
        FrictionFeedForward(-1.0, 0.0, 0.0)


@pytest.mark.parametrize(("M", "B", "coulomb_pos", "coulomb_neg"), [(0.1, 1.0, 0.5, 0.4), (2.0, 0.5, 1.0, 0.5), (0.001, 1.0, 0.3, 0.3)])
def test_friction_compensation_reduces_tracking_error(M, B, coulomb_pos, coulomb_neg):
    pi = design_pi(M, B, 1000.0)
    settings = CompensationSettings()
    amp = reference_amplitude(M, B, coulomb_pos, coulomb_neg, 5.0, 20.0, settings)
    ff = friction_feed_forward(B, coulomb_pos, coulomb_neg, settings.sign_band * amp)
    chk = check_compensation(M, B, coulomb_pos, coulomb_neg, pi, ff, 5.0, 20.0, settings)
    assert chk.with_ff.rms_error < 0.7 * chk.without_ff.rms_error
    assert chk.with_ff.max_error < chk.without_ff.max_error
    assert np.abs(chk.without_ff.u).max() <= 5.0


def test_wrong_compensation_does_not_help():
    # feed-forward with the Coulomb levels swapped in sign (friction doubled) makes tracking worse
    M, B = 0.1, 1.0
    pi = design_pi(M, B, 1000.0)
    r = 0.9 * np.sin(2 * math.pi * np.arange(2000) / 1000.0)
    plant = PlantParams(M=M, B=B, coulomb_pos=0.5, coulomb_neg=0.4)
    good = simulate_loop(plant, pi, r, 5.0, FrictionFeedForward(0.5, 0.4, B))
    none = simulate_loop(plant, pi, r, 5.0, None)
    too_much = simulate_loop(plant, pi, r, 5.0, FrictionFeedForward(2.0, 2.0, B))
    assert good.rms_error < none.rms_error < too_much.rms_error


def test_reference_amplitude_respects_the_limits():
    s = CompensationSettings()
    assert reference_amplitude(0.1, 1.0, 0.5, 0.4, 5.0, 20.0, s) == pytest.approx(0.9)
    assert reference_amplitude(0.1, 1.0, 0.5, 0.4, 5.0, 2.0, s) == pytest.approx(0.5)  # max_v / 4
    heavy = reference_amplitude(2.0, 0.5, 1.0, 0.5, 5.0, 20.0, s)
    assert (2.0 * 2 * math.pi + 0.5) * heavy + 1.0 <= 2.5 + 1e-9  # half of max_u drives it
    assert reference_amplitude(0.1, 1.0, 0.5, 0.4, 5.0, 20.0, CompensationSettings(ref_amplitude=3.0)) == 3.0
