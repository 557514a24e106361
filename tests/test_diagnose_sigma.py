"""The diagnosed model's 1-sigma hold: errors over stated sigma on plants with a known effect.

Hidden-effect plants (:mod:`servobench.bench.testing.hidden_effects`, white velocity-sensor
noise) with a Stribeck curve or a viscous asymmetry, a few seeds each, are diagnosed; every
parameter the diagnosis reports (the base as ``base_after``, the effect's parameters,
derived ones too) is compared with the plant's true value in units of its stated sigma.
The sigmas hold when those ratios have an rms near 1 (a wide band: a handful of cases) and
most lie within 2 sigma; a sigma 5 times too small or too large falls outside.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import servobench as sb
from servobench.bench.diagnose.data import prepare
from servobench.bench.diagnose.refit import evaluate, refit, with_covariance
from servobench.bench.diagnose.simulate import Candidate
from servobench.bench.log.io import read_log
from servobench.bench.report.diagnose import summary_lines
from servobench.bench.testing.hidden_effects import random_case, write_case_log

#: (hidden effect, seed) of each case: the diagnosis names the effect in each.
CASES = [("viscous_asymmetry", s) for s in (1, 2, 3, 4)] + [("stribeck", s) for s in (1, 2, 3, 5)]
#: Band of the rms of error / sigma over all parameters and cases, and the least share within 2 sigma.
RMS_BAND = (0.4, 2.5)
WITHIN_2_SIGMA = 0.75
BASE = ("M", "B", "coulomb_pos", "coulomb_neg")


def truth(case) -> dict[str, float]:
    """The plant's true values, keyed as the diagnosis' JSON ``std``."""
    p = case.params
    out = {"M": p.M, "B": p.B, "coulomb_pos": p.coulomb_pos, "coulomb_neg": p.coulomb_neg}
    if "stribeck" in case.effects:
        fs, vs = case.effects["stribeck"]["fs"], case.effects["stribeck"]["vs"]
        out |= {"stribeck.fs": fs, "stribeck.vs": vs, "stribeck.fs_pos": fs, "stribeck.fs_neg": fs}
    if "viscous_asymmetry" in case.effects:
        dB = case.effects["viscous_asymmetry"]["dB"]
        out |= {
            "viscous_asymmetry.dB": dB,
            "viscous_asymmetry.B_pos": p.B + dB,
            "viscous_asymmetry.B_neg": p.B - dB,
        }
    return {k: float(v) for k, v in out.items()}


def reported(doc: dict) -> dict[str, float]:
    """The final model's values in the JSON, keyed as its ``std``."""
    out = {k: doc["base_after"][k] for k in BASE}
    for e in doc["effects"]:
        out |= {f"{e['name']}.{k}": v for k, v in e["parameters"].items()}
    return out


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory) -> list[tuple[str, dict, dict, dict, list[str]]]:
    """``(effect, JSON, model.json record, true values, text lines)`` of each case."""
    folder = tmp_path_factory.mktemp("sigma")
    out = []
    for effect, seed in CASES:
        rng = np.random.default_rng(seed)
        case = random_case(effect, rng)
        log = sb.read_log(write_case_log(case, Path(folder) / f"{effect}{seed}.csv", rng))
        result = sb.diagnose(log)
        text = summary_lines(result.details)
        out.append((effect, result.to_dict(), result.model.to_dict(), truth(case), text))
    return out


def test_errors_over_sigma_hold(diagnosed):
    ratios = []
    for effect, doc, _, true, _ in diagnosed:
        assert [e["name"] for e in doc["effects"]] == [effect]
        values, std = reported(doc), doc["std"]
        for key, value in true.items():
            assert std.get(key) is not None and std[key] > 0, (effect, key, std)
            ratios.append((values[key] - value) / std[key])
    z = np.array(ratios)
    rms = math.sqrt(float(np.mean(z**2)))
    within = float(np.mean(np.abs(z) <= 2.0))
    assert RMS_BAND[0] <= rms <= RMS_BAND[1], (rms, np.round(z, 2))
    assert within >= WITHIN_2_SIGMA, (within, np.round(z, 2))


def test_every_fitted_parameter_has_a_sigma(diagnosed):
    for _, doc, model, _, _ in diagnosed:
        std = doc["std"]
        for key in (*BASE, "pole", "dc_gain"):
            assert isinstance(std.get(key), float) and std[key] > 0, (key, std)
        (entry,) = doc["effects"]
        for key in entry["parameters"]:
            sigma = std.get(f"{entry['name']}.{key}")
            assert isinstance(sigma, float) and sigma > 0, (entry, std)
        # model.json: the raw base and every effect parameter of the plant written.
        for name, params in model["effects"].items():
            for key in params:
                assert isinstance(model["std"].get(f"{name}.{key}"), float), (name, key)
        assert all(isinstance(model["std"].get(k), float) for k in BASE), model["std"]


def test_text_gives_value_plus_minus_sigma(diagnosed):
    effect, _, _, _, text = diagnosed[0]
    (line,) = [x for x in text if x.startswith(f"1. {effect} (")]
    assert line.count(" ± ") == len(line.split(", ")), line
    (base,) = [x for x in text if x.startswith("final base: ")]
    assert base.count(" ± ") == 6, base


def test_held_parameters_have_no_sigma(tmp_path):
    rng = np.random.default_rng(7)
    case = random_case("viscous_asymmetry", rng)
    data = prepare(read_log(write_case_log(case, tmp_path / "va.csv", rng)))
    p = case.params
    base = {"M": p.M, "B": p.B, "coulomb_pos": p.coulomb_pos, "coulomb_neg": p.coulomb_neg}
    fit = refit(data, Candidate(base, dict(case.effects)), bounds={})
    assert set(fit.std) == set(BASE)
    assert all(math.isfinite(s) and s > 0 for s in fit.std.values())


def test_a_candidate_taken_from_a_refit_gets_the_refit_s_sigma(tmp_path):
    """``with_covariance``: a candidate only evaluated (a term dropped from a refit) gets the
    sigma of the parameters the refit fitted, from a Jacobian at its values."""
    rng = np.random.default_rng(8)
    case = random_case("viscous_asymmetry", rng)
    data = prepare(read_log(write_case_log(case, tmp_path / "va.csv", rng)))
    p, dB = case.params, case.effects["viscous_asymmetry"]["dB"]
    base = {"M": p.M, "B": p.B, "coulomb_pos": p.coulomb_pos, "coulomb_neg": p.coulomb_neg}
    bounds = {"viscous_asymmetry": {"dB": (-0.9 * p.B, 0.9 * p.B)}}
    fit = refit(data, Candidate(base, {"viscous_asymmetry": {"dB": dB}}), bounds)
    assert set(fit.std) == {*BASE, "viscous_asymmetry.dB"}
    taken = evaluate(data, fit.candidate)
    assert taken.std == {}
    again = with_covariance(data, taken, fit)
    assert set(again.std) == set(fit.std)
    for key, sigma in fit.std.items():
        assert again.std[key] == pytest.approx(sigma, rel=0.05), key



#: ``diagnose_cases.py --seed 2``'s #277: a Stribeck curve 1.5 times the Coulomb level, one run
#: of 2 s read through sensor noise low-passed at about 8 Hz (lag-1 correlation of the
#: residual 0.8 at the diagnosis's 500 Hz), read again through :data:`NOISES` realisations of
#: that noise and refitted from the truth. The lag-window (HAC) sandwich gave the refits an
#: rms of error over sigma of 1.51-1.66 (82-84 % within 2 sigma) on three sets of 40
#: realisations; the noise model 1.12-1.20 (90-96 %).
COLOURED = ("stribeck", 1.5001049412179819, "single", "coloured", 216828066)
NOISES = 80
COLOURED_RMS = (0.8, 1.35)


def test_the_sigma_holds_under_coloured_sensor_noise(tmp_path):
    from servobench.bench.testing.sized_cases import sized_case

    effect, size, inputs, noise, seed = COLOURED
    z = []
    for k in range(NOISES):
        rng = np.random.default_rng(seed)
        case = sized_case(effect, rng, size, inputs=inputs, noise=noise)
        path = write_case_log(case, tmp_path / f"{k}.csv", rng, noise_seed=7919 * k + 13)
        true, s = truth(case), case.effects["stribeck"]
        bounds = {name: (0.3 * s[name], 3.0 * s[name]) for name in ("fs", "vs")}
        start = Candidate({k: true[k] for k in BASE}, {"stribeck": dict(s)})
        fit = refit(prepare(read_log(path)), start, {"stribeck": bounds})
        got = {**fit.candidate.base, **{f"stribeck.{k}": v for k, v in fit.candidate.effects["stribeck"].items()}}
        z += [(got[key] - true[key]) / fit.std[key] for key in (*BASE, "stribeck.fs", "stribeck.vs")]
    z = np.asarray(z)
    rms = float(np.sqrt(np.mean(z**2)))
    assert COLOURED_RMS[0] <= rms <= COLOURED_RMS[1], rms
    assert np.mean(np.abs(z) < 2.0) >= 0.87


def test_a_positive_parameter_whose_sigma_exceeds_its_value_is_not_determined():
    """``M`` and ``B`` cannot be negative: a first-order sigma beyond the value says the log does
    not determine it (a ``B`` fitted to 1e-6 for a true 1.0 on a log as noisy as its signal
    stated 1.4e-6 +- 2e-5), and it is NaN, not a bar that reaches below zero."""
    from servobench.bench.diagnose.sigma import natural_covariance

    rng = np.random.default_rng(4)
    J = rng.normal(size=(600, 4))
    r = rng.normal(size=600)
    names = ("M", "B", "coulomb_pos", "coulomb_neg")
    sd = natural_covariance(names, (0.1, 1.0, 0.5, 0.4), J, r, [300, 600], (1.0,) * 4).std
    assert all(0.0 < sd[k] < 0.1 for k in names), sd  # each about 1 / sqrt(600)
    tiny = natural_covariance(names, (0.1, 0.01, 0.5, 0.4), J, r, [300, 600], (1.0,) * 4).std
    assert math.isnan(tiny["B"]) and all(0.0 < tiny[k] < 0.1 for k in ("M", "coulomb_pos", "coulomb_neg"))
