"""Issue 24, defect 4: a strong Stribeck curve is named alone, and its fit closes the gap.

The axis of issue 12's strong case -- a Stribeck peak 2.5 times the Coulomb
level on a weakly damped axis -- excited by one square-wave run and by a SIDBE
pair with quiet sensors (velocity noise 0.001). Its best linear-plus-Coulomb
fit wants a negative viscous coefficient, so the current base model (B held
near zero, Coulomb levels twice the true ones) is a poor place to start the
Stribeck curve from: refitted from there alone the curve stuck at B = 0.15,
Coulomb 0.76 / 0.68 (true 0.3, 0.5 / 0.4) and left a gap of 0.79 % against a
noise floor of 0.18 % -- "unexplained" for a plant inside the library, and a
residual a second effect could soak up. The refit now starts from the
screening's own joint fit too when the two bases are far apart
(:func:`servobench.bench.diagnose.screening.unsettled`), and a term joining a
model that already holds an effect must pay against that model refitted
without it (:func:`servobench.bench.diagnose.search._refit_ablate`).

Issue 30, over-naming on a new user's logs: a plant simulated finely outside
the library (:mod:`servobench.bench.testing.fine_plant`) whose Stribeck
breakaway is added to each direction's Coulomb level, so its static level
differs by direction. A square-wave run named ``stribeck`` and ``cogging``, a
strong-Stribeck SIDBE pair ``stribeck`` and ``backlash`` (the library's curve
holds one static level, and a second effect soaked up the difference). The
curve is now fitted with a static level per direction
(:data:`servobench.bench.diagnose.screening.COMPANIONS`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.log.io import read_log
from servobench.bench.testing.fine_plant import ISSUE_PLANTS, write_issue_log
from servobench.bench.testing.hidden_effects import HiddenCase, write_case_log
from servobench.sim_backend.physics.plant import PlantParams

pytestmark = pytest.mark.slow  # two diagnoses

#: The generator's seed of each log.
SEED = 5


#: Velocity-sensor noise of each log.
NOISE = {"square": 0.004, "sidbe": 0.001}


def strong_stribeck(inputs: str) -> HiddenCase:
    """Stribeck peak 1.25 = 2.5 times the Coulomb level 0.5, B = 0.3."""
    p = PlantParams(M=0.1, B=0.3, coulomb_pos=0.5, coulomb_neg=0.4, noise=NOISE[inputs])
    effects = {"stribeck": {"fs": 1.25, "vs": 0.8}}
    return HiddenCase("stribeck", p.with_changes(effects=effects), 1.4, effects, inputs)


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory):
    folder = tmp_path_factory.mktemp("overnaming")
    out = {}
    for inputs in ("square", "sidbe"):
        rng = np.random.default_rng(SEED)
        path = write_case_log(strong_stribeck(inputs), Path(folder) / f"{inputs}.csv", rng)
        out[inputs] = diagnose(read_log(path))
    return out


@pytest.mark.parametrize("inputs", ["square", "sidbe"])
def test_only_the_stribeck_curve_is_named(diagnosed, inputs):
    d = diagnosed[inputs]
    assert [e.name for e in d.effects] == ["stribeck"], [e.name for e in d.effects]
    assert d.effects[0].parameters["fs"] == pytest.approx(1.25, rel=0.1)


@pytest.mark.parametrize("inputs", ["square", "sidbe"])
def test_the_stribeck_fit_closes_the_gap_to_its_noise_floor(diagnosed, inputs):
    d = diagnosed[inputs]
    assert d.verdict.verdict == "explained", d.verdict.headline()
    assert d.gap_after <= 1.5 * d.verdict.floor.percent
    assert d.gap_after <= 0.2 * d.gap_before, (d.gap_before, d.gap_after)


def test_the_sidbe_pair_finds_the_plant_s_own_friction(diagnosed):
    d = diagnosed["sidbe"]
    b, s = d.base, d.effects[0].parameters
    assert b["B"] == pytest.approx(0.3, rel=0.05)
    assert (b["coulomb_pos"], b["coulomb_neg"]) == pytest.approx((0.5, 0.4), abs=0.02)
    assert s["vs"] == pytest.approx(0.8, rel=0.05)


def test_every_rejected_second_effect_says_why(diagnosed):
    for d in diagnosed.values():
        for rnd in d.trace.rounds:
            assert all(t.reason for t in rnd.tried), [(t.effects, t.reason) for t in rnd.tried]


@pytest.fixture(scope="module")
def issue30(tmp_path_factory):
    folder = Path(tmp_path_factory.mktemp("issue30"))
    return {
        kind: diagnose(
            read_log(write_issue_log(kind, folder / f"{kind}.csv", np.random.default_rng(30)))
        )
        for kind in ("square", "sidbe")
    }


@pytest.mark.parametrize("kind", ["square", "sidbe"])
def test_issue30_names_the_stribeck_curve_alone(issue30, kind):
    d = issue30[kind]
    assert [e.name for e in d.effects] == ["stribeck"], [e.name for e in d.effects]
    assert d.gap_after <= d.gap_before / 3, (d.gap_before, d.gap_after)


@pytest.mark.parametrize("kind", ["square", "sidbe"])
def test_issue30_refits_the_stribeck_curve_within_5_percent(issue30, kind):
    d, plant = issue30[kind], ISSUE_PLANTS[kind]
    s, b = d.effects[0].parameters, d.base
    assert s["vs"] == pytest.approx(plant.vs, rel=0.05)
    assert s["fs_pos"] == pytest.approx(plant.fc_pos + plant.fs, rel=0.05)
    assert s["fs_neg"] == pytest.approx(plant.fc_neg + plant.fs, rel=0.05)
    # The breakaway excess over each direction's Coulomb level.
    assert s["fs_pos"] - b["coulomb_pos"] == pytest.approx(plant.fs, rel=0.05)
    assert s["fs_neg"] - b["coulomb_neg"] == pytest.approx(plant.fs, rel=0.05)
    assert (b["M"], b["B"]) == pytest.approx((plant.M, plant.B), rel=0.05)


def test_issue30_sidbe_pair_closes_the_gap_to_the_noise_floor(issue30):
    d = issue30["sidbe"]
    assert d.gap_after <= 1.5 * d.verdict.floor.percent, (d.gap_after, d.verdict.floor.percent)
