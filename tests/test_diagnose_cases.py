"""Issue 30: a handful of the naming benchmark's random cases (``benchmarks/diagnose_cases.py``).

Each is a case of ``--cases 300 --seed 1`` (its number there in the name; three of ``--seed 2``, one of 3), with
its size, excitation and sensor noise: the four excitations (SIDBE pair, single
run, square wave, closed loop in a travel window), the three noises (white,
coloured, quantised), a control with nothing hidden and a Stribeck curve. The
hidden effect must be named alone, the gap shrink at least 3 times where it is
at least 3 times the noise floor, and a Stribeck curve be refitted within 5 %.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.diagnose.search import FLOOR_FACTOR
from servobench.bench.diagnose.workflow import diagnose
from servobench.bench.log.io import read_log
from servobench.bench.report.diagnose import summary_lines, to_json
from servobench.bench.testing.hidden_effects import CaseResults, true_floor, write_case_log
from servobench.bench.testing.sized_cases import sized_case

pytestmark = pytest.mark.slow  # a score of diagnoses, one after the other

#: ``number: (effect, size, inputs, noise, seed)``, as the benchmark draws them.
CASES = {
    1: ("stribeck", 2.8716236178431096, "sidbe", "white", 669652944),
    2: ("viscous_asymmetry", 1.5583161224314392, "single", "quantised", 551886181),
    6: ("cogging", 1.6337447237016287, "closed", "white", 823155374),
    23: ("position_friction", 2.6913427410414514, "closed", "white", 1013418405),
    76: ("time_delay", 2.515089268817809, "square", "coloured", 913638093),
    108: (None, 0.8304471040479893, "sidbe", "coloured", 990144555),
    # Cogging wells deeper than the breakaway: the refit must search the base friction with
    # the amplitude (a rugged surface), and a trapped axis travels under two periods.
    222: ("cogging", 2.089137430271495, "single", "coloured", 1719139267),
    270: ("cogging", 1.859965857405888, "sidbe", "coloured", 919936532),
    # A square wave through wells 2.8 times the Coulomb level: the screened phase misses the
    # narrow basin by about 0.05 rad, so the refit scans the phase in offsets [rad] before the
    # base friction (scanned first, the friction bent to the wrong wells: train gap 2.9 % where
    # the hidden model gives 0.54 %, held-out 9.9 %, nothing named).
    198: ("cogging", 2.824020572734966, "square", "quantised", 2120246618),
    # A single run held by wells 2.9 times the Coulomb level: the axis travels 0.73 of their
    # period, and the quick guess of cogging ranks it neither among the best two guesses nor the
    # best three scores; as a rugged effect it is refitted all the same (a saturation was named,
    # gap 92 % -> 52 %).
    126: ("cogging", 2.8675154218392254, "single", "coloured", 417937508),
    # A play whose first refit sticks in a poor optimum: a second term (a Stribeck curve, a
    # viscous asymmetry) soaks up its residual until the play's rugged parameters are scanned
    # again in the model without that term.
    56: ("backlash", 0.6927095212513469, "sidbe", "coloured", 1206594658),
    188: ("backlash", 2.5130652670773643, "single", "white", 1027945035),
    # Closed loop hunting in a play, simulated in windows of 0.5 s from the measured state: each
    # window carries on the play's engaged side and load from the one before (restarted relaxed,
    # the hidden model itself left a gap of 24.8 % for 0.97 % over the whole run), and the base
    # fit, which starts without friction, reaches the Coulomb levels (it kept 0.0 / 0.006 for
    # 0.28 / 0.43: gap 63 % -> 22 %, held to halve; now 39 % -> 3.5 %).
    164: ("backlash", 2.93533607371622, "closed", "white", 1446883356),
    # A PI loop's command through a quantizer of 0.49: the simulation is good only within about a
    # per cent of the step (0.4985 leaves 4.4 % where 0.4905 leaves 1.6 %). The screening refined
    # only around its three best coarse steps, all beside a wrong one, and nothing was named (gap
    # 3.56 % for a true floor of 1.10 %): it refines around the best of each neighbourhood now,
    # and offers the others to the quick simulation.
    166: ("quantization", 1.0249900125293114, "closed", "quantised", 1056561942),
    # A resonance in a SIDBE pair, white noise: the velocity's own second differences carry the
    # mode's ringing after every switch (floor 1.29 % for a true 0.63 %); the residual's against
    # the final model carry only what it misses.
    137: ("resonance", 1.1087317800702063, "sidbe", "white", 1060869281),
    # A play under a square wave of one level: the steady state fixes only the Coulomb level plus
    # B times the speed, and the base, fitted without the play, split it wrongly (Coulomb 1.04
    # for 0.21, B 0.43 for 0.98); the play's refit stalled half-way along that line (gap
    # 11.3 % -> 4.2 %). Restarts along the line, each refitted, reach the play (1.5 %).
    272: ("backlash", 2.5891902309098977, "square", "quantised", 1876360588),
}
#: Cases of other seeds, keyed by seed and number.
OTHER_SEEDS = {
    # A play 2.8 times the Coulomb level in a SIDBE pair. The base fitted without it is far off
    # (M 0.033 for 0.082, Coulomb 0 / 0.16 for 0.42 / 0.46), and on that base the play's quick
    # guess simulated worse than the base (35.7 % held out against 34.8 %): it was never
    # refitted, and nothing was named (gap 28.6 %). Against the base alone, far from the floor,
    # every effect is refitted once nothing paid.
    "2-236": ("backlash", 2.822980818549884, "sidbe", "coloured", 1307834303),
    # Cogging wells 2.7 times the Coulomb level under a square wave: the periodogram of the base
    # fit's residual put the period 1.2 % long (the base's direction column had taken up part of
    # the wells), a drift of a tenth of a period over the travel's eight, and the refit stuck
    # there (held out 12.7 % for the hidden model's 0.46 %: nothing named). The joint
    # regression settles the period.
    "2-234": ("cogging", 2.7287800340935675, "square", "white", 119894916),
    # Wells 1.9 times the Coulomb level in a SIDBE pair: the guess simulated on the current base
    # (its friction 1.5 times the joint fit's) ranked above the joint base, whose refit alone
    # reaches the wells; a rugged effect's refit starts from both.
    "2-54": ("cogging", 1.8984429688621913, "sidbe", "quantised", 1346077885),
    # A play 1.7 times the Coulomb level in a single run, its base as far off (M
    # 0.097 for 0.149) and its residual as unpredictable from the log's signals as coloured
    # noise (12 %): refitted only because every effect is, against the base alone.
    "3-20": ("backlash", 1.6992098087806875, "single", "white", 456516547),
}
NAMED = {**CASES, **OTHER_SEEDS}
#: A Stribeck curve whose static level is four times the Coulomb level, in a single run, read in
#: steps: the axis mostly sticks, and what little motion there is stays under the Stribeck
#: velocity. The base fit puts its Coulomb levels at the breakaway (1.78 / 1.75 for 0.40 / 0.46)
#: with B near zero, and no curve over those levels moves the axis at all: nothing was named
#: (gap 76 %). Restarts that take the base's level as the static one and lower the Coulomb
#: levels under it reach the curve's basin (the training data do not place it further: the
#: hidden model's own training gap is no lower than the refit's).
BREAKAWAY = {157: ("stribeck", 2.968598356790718, "single", "quantised", 871854249)}
#: A Stribeck curve whose static level the command barely reaches: the velocity never leaves a step
#: of its reading. The best base in motion creeps (B 65 where the axis stands: gap 328 %), and a
#: dead zone was named for stopping the creep; a base held at rest leaves the noise floor.
AT_REST = {61: ("stribeck", 2.617495926584324, "single", "quantised", 267276528)}
#: A two-level SIDBE pair through a quantized command: each run's two levels only move, which a
#: saturation or a dead zone does as well. The report must say the log cannot tell them apart.
TIED = {82: ("quantization", 2.330902093314011, "sidbe", "coloured", 539334954)}
#: Coloured noise under a residual the log's signals predict: the floor from second differences
#: (0.69 % and 0.16 %) is far under the true one (2.29 % and 0.35 %), which the bar's upper end,
#: the part no signal predicts, reaches. A weak Stribeck curve in a single run, a resonance
#: named in a square wave.
COLOURED = {
    193: ("stribeck", 0.5496469328981458, "single", "coloured", 620095089),
    17: ("resonance", 1.150243619343058, "square", "coloured", 1803631832),
}


#: Cases whose true floor lay outside the stated floor's bar: a time delay in closed loop (true
#: floor 2.63 % over the period scatter's 1.62 %: the loop's reaction cancels part of the noise
#: from one period to the next), a mode under a square wave (0.399 % over a bound of 0.358 %,
#: read from a coloured residual's few independent samples), and a play under a single run
#: (1.20 % under a floor of 2.10 % that the residual no signal predicts raised from the
#: measurement's).
BARS = {
    64: ("time_delay", 1.4751863798496543, "closed", "quantised", 24261516),
    125: ("resonance", 1.1250458498300282, "square", "coloured", 857470922),
    248: ("backlash", 2.6400207615279028, "single", "coloured", 118051074),
}


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    folder = Path(tmp_path_factory.mktemp("cases"))

    def run(number: int) -> dict:
        effect, size, inputs, noise, seed = {**NAMED, **TIED, **COLOURED, **BREAKAWAY, **AT_REST, **BARS}[number]
        rng = np.random.default_rng(seed)
        case = sized_case(effect, rng, size, inputs=inputs, noise=noise)
        log = read_log(write_case_log(case, folder / f"case-{number}.csv", rng))
        return {"case": case, "diagnosis": diagnose(log), "log": log}

    return CaseResults(run)


@pytest.mark.parametrize("number", [*sorted(CASES), *OTHER_SEEDS])
def test_the_hidden_effect_is_named_alone(results, number):
    effect = NAMED[number][0]
    d = results[number]["diagnosis"]
    assert [e.name for e in d.effects] == ([effect] if effect else []), d.trace.stop


@pytest.mark.parametrize("number", [*sorted(CASES), *OTHER_SEEDS])
def test_the_gap_shrinks_three_times_where_it_shows(results, number):
    d = results[number]["diagnosis"]
    if d.gap_before >= 3 * d.verdict.floor.percent and NAMED[number][0]:
        assert d.gap_after <= d.gap_before / 3, (d.gap_before, d.gap_after)


def test_the_stribeck_curve_is_refitted_within_5_percent(results):
    case, d = results[1]["case"], results[1]["diagnosis"]
    true, got = case.effects["stribeck"], d.effects[0].parameters
    assert got["vs"] == pytest.approx(true["vs"], rel=0.05)
    assert (got["fs_pos"], got["fs_neg"]) == pytest.approx((true["fs"], true["fs"]), rel=0.05)


@pytest.mark.parametrize("number", sorted(BREAKAWAY))
def test_a_stribeck_curve_over_an_axis_that_mostly_sticks_is_named(results, number):
    d = results[number]["diagnosis"]
    assert [e.name for e in d.effects] == ["stribeck"], d.trace.stop
    held = [s.fit.gap_held_out for s in d.steps]
    assert held[-1] <= held[0] / 2, held


@pytest.mark.parametrize("number", sorted(BREAKAWAY))
def test_a_residual_the_axis_at_rest_does_not_show_is_no_coloured_noise(results, number):
    """The refitted curve still places the slips wrongly (38 % off): its residual, spikes at
    each slip, is one no signal predicts, and counted as coloured noise it put the floor at
    three times the true one and the verdict at "explained". Where the model holds the axis at
    rest (most of this log), the residual is noise alone plus what the model misses there: it
    bounds the floor near the truth, and the verdict says what is left."""
    r = results[number]
    d = r["diagnosis"]
    floor, true = d.verdict.floor, true_floor(r["log"], r["case"])
    assert floor.rest_percent is not None and floor.percent == floor.rest_percent, floor.source
    assert true <= floor.percent <= 1.5 * true, (floor.percent, true)
    assert floor.source.startswith("the residual where the model holds the axis at rest")
    assert d.verdict.verdict == "unexplained", d.verdict
    shown = [line for line in summary_lines(d) if line.startswith("noise floor ")]
    assert shown[0].startswith(f"noise floor {floor.percent:.3g}% (the noise lies between "
                               f"{floor.lower_percent:.3g}% and {floor.upper_percent:.3g}%; "), shown  # fmt: skip
    assert floor.lower_percent < floor.percent < floor.upper_percent


@pytest.mark.parametrize("number", sorted(BARS))
def test_the_true_floor_lies_within_the_stated_floors_bar(results, number):
    """The bar runs from the measurement's floor (where a bound of the residual raised the
    floor: that bound may hold structure no signal predicts) to the upper bound widened by two
    of its own sampling errors (without the period scatter in closed loop); the benchmark's
    10 % either side."""
    r = results[number]
    floor, true = r["diagnosis"].verdict.floor, true_floor(r["log"], r["case"])
    assert 0.9 * floor.lower_percent <= true <= 1.1 * floor.upper_percent, (
        floor.lower_percent, true, floor.upper_percent, floor.source)  # fmt: skip
    shown = to_json(r["diagnosis"])["noise"]
    assert (shown["lower_percent"], shown["upper_percent"]) == (floor.lower_percent, floor.upper_percent)


@pytest.mark.parametrize("number", sorted(AT_REST))
def test_an_axis_that_does_not_move_names_nothing_and_says_why(results, number):
    d = results[number]["diagnosis"]
    lines = summary_lines(d)
    assert d.effects == (), [e.name for e in d.effects]
    assert d.verdict.gap_percent <= FLOOR_FACTOR * d.verdict.floor.percent, d.verdict
    note = [n for n in d.notes if n.startswith("the axis does not move")]
    assert len(note) == 1 and "excite with a larger command" in note[0], d.notes
    base = d.steps[-1].fit.candidate.base
    top = max(float(np.max(np.abs(r.u))) for r in d.data.segments)
    assert base["coulomb_pos"] == base["coulomb_neg"] == top
    shown = [line for line in lines if line.startswith("final base: ")]
    assert shown[0].endswith("(no 1-sigma: the log does not determine them)"), shown


def test_a_log_of_sensor_noise_alone_is_held_at_rest(tmp_path):
    """A command under the breakaway, a velocity read in steps of 0.01 that only the noise
    moves: the best base in motion creeps no better than an axis at rest (M and B of 1e14 and
    more), and the log shows nothing to name."""
    rng = np.random.default_rng(1)
    t = np.arange(4000) / 1000.0
    u = 0.3 * np.sign(np.sin(2 * np.pi * t))
    rows = [f"{run},{t[k]},{scale * u[k]},{0.01 * round(0.4 * rng.normal())}"
            for run, scale in ((1, 1.0), (2, 0.9)) for k in range(t.size)]  # fmt: skip
    path = tmp_path / "log.csv"
    path.write_text("# fs = 1000\nrun,t,u,v\n" + "\n".join(rows) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a model at rest divides by its zero gain nowhere
        d = diagnose(read_log(path))
        findings = to_json(d)["findings"]
    assert d.effects == ()
    assert [n for n in d.notes if n.startswith("the axis does not move")], d.notes
    assert any("undetermined" in f for f in map(str, findings)), findings
    base = d.steps[-1].fit.candidate.base
    assert base["coulomb_pos"] == base["coulomb_neg"] == pytest.approx(0.3)


@pytest.mark.parametrize("number", sorted(TIED))
def test_effects_the_log_cannot_tell_apart_are_reported_as_rivals(results, number):
    effect = TIED[number][0]
    d = results[number]["diagnosis"]
    assert len(d.effects) == 1, d.trace.stop
    first = d.effects[0]
    assert effect in (first.name, *first.rivals), (first.name, first.rivals)
    assert first.rivals, "the effects that fit as well are not reported"
    assert d.gap_after <= d.gap_before / 3, (d.gap_before, d.gap_after)
    note = [n for n in d.notes if "cannot tell them apart" in n]
    assert len(note) == 1 and first.name in note[0] and all(r in note[0] for r in first.rivals)
    assert to_json(d)["effects"][0]["rivals"] == list(first.rivals)


@pytest.mark.parametrize("number", sorted(COLOURED))
def test_coloured_noise_under_a_structured_residual_is_within_the_floors_bar(results, number):
    r = results[number]
    d = r["diagnosis"]
    floor, true = d.verdict.floor, true_floor(r["log"], r["case"])
    assert true > 2 * floor.percent  # second differences see the low-passed noise only in part
    assert floor.percent <= true <= 1.1 * floor.upper_percent, floor.source
    assert "coloured noise, which second differences see only in part" in floor.source
    assert f"coloured noise could reach {floor.upper_percent:.3g}%" in d.verdict.signature
    assert to_json(d)["noise"]["upper_percent"] == floor.upper_percent


@pytest.mark.parametrize("number", [n for n in sorted(CASES) if CASES[n][3] == "quantised"] + [137])
def test_the_stated_floor_is_the_gap_the_hidden_model_leaves(results, number):
    """A velocity read in steps about three times its noise, and white noise under a ringing
    mode: the floor the report states is within 10 % of the true one, the gap the hidden model
    itself leaves on the log (before, the noise and the rounding were added as if independent:
    1.5 times the true floor at the median of the benchmark's quantised cases; and the mode's
    ringing counted as noise)."""
    r = results[number]
    floor = r["diagnosis"].verdict.floor
    assert floor.percent == pytest.approx(true_floor(r["log"], r["case"]), rel=0.1), floor.source
