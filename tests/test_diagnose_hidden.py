"""Hidden-effect logs: diagnose sees only the log, must name the effect first and shrink the gap.

Each library effect is hidden, with random parameters (explicit seeds) and
velocity-sensor noise, in a random base plant; a control plant hides
nothing. Each case is diagnosed once, in the test worker, the first time a
test reads it, and shared across the module. One case streams through the real ``sim://`` drive and runner instead of the
plant directly, so the effect's URL keys are exercised end to end.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.log.io import read_log
from servobench.bench.testing.hidden_effects import (
    CASE_FS_HZ,
    CaseResults,
    case_commands,
    random_case,
    write_case_log,
)
from servobench.sim_backend.physics import effects as library

pytestmark = pytest.mark.slow  # twelve hidden-effect diagnoses, one after the other

#: Seed of each case's generator (plant, parameters, excitation, noise).
SEEDS = {name: 100 + i for i, name in enumerate(library.names())} | {None: 99}
#: The case streamed through SimDrive + stream_runs.
STREAMED = "stribeck"
#: Required gap shrink factor.
SHRINK = 3.0


def stream_case_log(case, path: Path, rng: np.random.Generator) -> Path:
    """The case's runs through ``servobench.drivers.sim.SimDrive`` (from its sim:// URL) and the runner."""
    from servobench.bench.run.runner import stream_runs
    from servobench.drivers.sim import SimDrive

    url = case.sim_url() + f"&seed={int(rng.integers(2**31))}&pace=fast"
    with SimDrive(url) as drive:
        stream_runs(drive, case_commands(case, rng), CASE_FS_HZ, path, settle_s=1.0)
    return path


def run_case(effect: str | None, folder: str) -> dict:
    rng = np.random.default_rng(SEEDS[effect])
    case = random_case(effect, rng)
    path = Path(folder) / f"{effect or 'control'}.csv"
    writer = stream_case_log if effect == STREAMED else write_case_log
    log = read_log(writer(case, path, rng))
    d = diagnose(log)
    return {
        "named": [e.name for e in d.effects],
        "parameters": [e.parameters for e in d.effects],
        "evidence": [e.evidence for e in d.effects],
        "before": d.gap_before,
        "after": d.gap_after,
        "truth": case.effects,
        "columns": sorted(("t_host",) if "t_host" in log.runs[0].extra else ()),
        "families": [f.as_dict() for f in d.families],
        "coulomb_truth": (case.params.coulomb_pos, case.params.coulomb_neg),
    }


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> CaseResults:
    folder = str(tmp_path_factory.mktemp("hidden"))
    return CaseResults(lambda effect: run_case(effect, folder))


@pytest.mark.parametrize("effect", library.names())
def test_hidden_effect_is_named_first_and_the_gap_shrinks(results, effect):
    r = results[effect]
    assert r["named"][:1] == [effect], r
    assert r["before"] >= SHRINK * r["after"], r
    assert r["evidence"][0]


def test_nothing_hidden_names_nothing(results):
    r = results[None]
    assert r["named"] == [] and r["after"] == r["before"]


def test_the_streamed_case_went_through_the_drive_and_runner(results):
    assert results[STREAMED]["columns"] == ["t_host"]


@pytest.mark.parametrize(
    "effect, parameter, rel",
    [
        ("viscous_asymmetry", "dB", 0.1),
        ("time_delay", "delay", 0.1),
        ("saturation", "limit", 0.1),
        ("deadzone", "width", 0.15),
        ("stribeck", "fs", 0.15),
        ("resonance", "wn", 0.1),
        ("cogging", "period", 0.05),
    ],
)
def test_named_parameters_are_close_to_the_hidden_ones(results, effect, parameter, rel):
    r = results[effect]
    assert r["parameters"][0][parameter] == pytest.approx(r["truth"][effect][parameter], rel=rel)


def test_a_named_offset_is_reported_with_the_coulomb_levels_as_one_family(results):
    r = results["offset"]
    assert [f["parameters"] for f in r["families"]] == [["offset", "coulomb_pos", "coulomb_neg"]]
    family = r["families"][0]
    offset = r["parameters"][0]["offset"]
    lo, hi = family["offset_range"]
    assert lo <= offset <= hi and "one family" in family["sentence"]
    # What the data fix, whatever the split: the friction net of the offset, as hidden.
    fcp, fcn = r["coulomb_truth"]
    o = r["truth"]["offset"]["offset"]
    assert family["net_pos"] == pytest.approx(fcp - o, rel=0.1)
    assert family["net_neg"] == pytest.approx(fcn + o, rel=0.1)
