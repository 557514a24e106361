"""The stated 1-sigma cover the error (issue 30 §3): a small seed set of the coverage benchmark.

``benchmarks/sigma_coverage.py`` measures it on 200 seeds of each noise kind; here a
few seeds of white and of coloured (AR(1)) velocity noise on a shorter SIDBE pair
hold the rms of error over sigma in a wide band and most errors within 2 sigma.
The textbook ``s^2 (J^T J)^-1`` of the output-error fit failed the coloured half
(rms of error over sigma about 4, a quarter within 2 sigma).
"""

import math

import pytest

from servobench.bench.testing.coverage import PARAMETERS, clean_log, coverage_case, summarise

pytestmark = pytest.mark.slow

SEEDS = range(1, 9)
#: Honest sigmas give rms 1 and 95 % within 2 sigma; eight seeds scatter the rms by about 0.25.
RMS_BAND = (0.6, 1.6)
WITHIN_2 = 0.8


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return clean_log(tmp_path_factory.mktemp("coverage") / "clean", periods=3, period_s=2.0)


@pytest.mark.parametrize("kind", ["white", "coloured"])
def test_the_stated_sigma_covers_the_error(clean, kind):
    cases = [coverage_case(clean, kind, seed, "joint") for seed in SEEDS]
    figures = summarise(cases)
    pooled = [abs(c["error"][k]) / c["std"][k] for c in cases for k in PARAMETERS[:4]]
    for key in PARAMETERS[:4]:
        s = figures[key]
        assert s["unstated"] == 0, (key, s)
        assert RMS_BAND[0] <= s["rms"] <= RMS_BAND[1], (key, s)
    assert sum(z <= 2.0 for z in pooled) / len(pooled) >= WITHIN_2, figures
    delay = figures["delay_s"]  # the true delay, 0, is on its bound: covered, not necessarily tight
    assert delay["within2"] >= WITHIN_2 and not math.isnan(delay["rms"]), delay
    if kind == "coloured":
        assert all(any("coloured" in n for n in c["notes"]) for c in cases)


@pytest.fixture(scope="module")
def delayed(tmp_path_factory):
    return clean_log(
        tmp_path_factory.mktemp("coverage") / "delayed", periods=3, period_s=2.0, delay_s=DELAY_S
    )


#: A plant delay inside the range [s]: the delay's truth off its bound, where its rms is 1 too.
DELAY_S = 0.0004


def test_the_delay_s_sigma_covers_its_error_off_its_bound(delayed):
    cases = [coverage_case(delayed, "white", seed, "joint", DELAY_S) for seed in SEEDS]
    delay = summarise(cases)["delay_s"]
    assert delay["unstated"] == 0, delay
    assert RMS_BAND[0] <= delay["rms"] <= RMS_BAND[1], delay
    assert delay["within2"] >= WITHIN_2, delay
    assert all(abs(c["error"]["delay_s"]) < 0.5 * DELAY_S for c in cases), cases


@pytest.fixture(scope="module")
def clean_default(tmp_path_factory):
    """The benchmark's pair: 4 periods of 4 s per run (three steady periods to read the FRF's
    noise from: the shorter pair's two leave that sigma itself too uncertain to judge)."""
    return clean_log(tmp_path_factory.mktemp("coverage") / "default")


def test_the_sidbe_methods_sigma_covers_its_friction_leakage(clean_default):
    """``--method sidbe`` at amplitude 1 (the published estimate): friction leaks into the
    differential FRF and M comes out some 20 % low, a bias the noise's sigma (3 %) did not
    cover (rms of error over sigma 4.3-4.8, under a fifth within 2 sigma). The leakage, simulated
    at the model, is in the sigma now, and the estimate says so."""
    cases = [coverage_case(clean_default, "white", seed, "sidbe") for seed in SEEDS]
    figures = summarise(cases)
    for key in PARAMETERS[:4]:
        s = figures[key]
        assert s["unstated"] == 0, (key, s)
        assert RMS_BAND[0] <= s["rms"] <= RMS_BAND[1], (key, s)
        assert s["within2"] >= WITHIN_2, (key, s)
    assert all(c["estimator"] == "sidbe/frf" for c in cases)
    assert all(abs(c["error"]["M"]) > 0.05 * 0.1 for c in cases)  # the bias is there to cover
    assert all(any("friction leaks into the differential FRF" in n for n in c["notes"]) for c in cases)


def test_a_parameter_the_residual_does_not_move_leaves_the_others_their_sigma():
    """A Jacobian column of zeros (a parameter no sample responds to) makes that parameter
    undetermined (NaN), not every parameter: the others' sigma is the covariance without it."""
    import numpy as np

    from servobench.bench.identify.covariance import hac_covariance

    rng = np.random.default_rng(3)
    J = rng.normal(size=(400, 3))
    r = rng.normal(size=400)
    alone = hac_covariance(J, r)
    widened = hac_covariance(np.column_stack((J[:, :2], np.zeros(400), J[:, 2:])), r)
    assert np.all(np.isnan(widened[2])) and np.all(np.isnan(widened[:, 2]))
    kept = [0, 1, 3]
    assert np.allclose(widened[np.ix_(kept, kept)], alone, rtol=1e-12, atol=0.0)
    assert np.all(np.isfinite(alone)) and np.all(np.diag(alone) > 0)
