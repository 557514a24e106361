"""The diagnosis' parts: data preparation, gap, noise floor, signatures, refit."""

from __future__ import annotations

import math

import numpy as np
import pytest

from servobench.bench.diagnose.data import DEFAULT_HORIZON_S, noise_floor_percent, prepare
from servobench.bench.diagnose.refit import refit
from servobench.bench.diagnose.signatures import compute_signatures
from servobench.bench.diagnose.simulate import Candidate, gap_percent, simulate
from servobench.bench.identify.derivative import differentiate_position
from servobench.bench.log.io import ExperimentLog, RunData
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.physics.plant import simulate as plant_simulate

FS = 500.0


def make_log(runs, metadata=None) -> ExperimentLog:
    return ExperimentLog(tuple(runs), dict(metadata or {}), FS, True, "test")


def binary(n: int, seed: int, amp: float = 2.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.choice([-amp, amp], n // 40 + 1), 40)[:n] * rng.uniform(0.5, 1.0, n)


def plant_log(params: PlantParams, n: int = 1000, seed: int = 1) -> ExperimentLog:
    runs = []
    for number in (1, 2):
        u = binary(n, seed + number, 2.0 * number)
        v, x = plant_simulate(u, FS, params, np.random.default_rng(seed))
        runs.append(RunData(number, np.arange(n) / FS, u, v, x))
    return make_log(runs)


def test_velocity_from_position_is_zero_phase():
    t = np.arange(2000) / 1000.0
    x = np.sin(2 * math.pi * 2.0 * t)
    v = differentiate_position(x, 1000.0).v
    inner = slice(100, -100)
    assert (
        np.max(np.abs(v[inner] - 2 * math.pi * 2.0 * np.cos(2 * math.pi * 2.0 * t[inner]))) < 0.02
    )


def test_prepare_holds_out_three_blocks_per_run_and_derives_missing_velocity():
    n = 1000
    x = np.cumsum(binary(n, 3)) / FS
    data = prepare(make_log([RunData(1, np.arange(n) / FS, binary(n, 3), None, x)]))
    held_out = data.held_out[0]
    assert data.derived and data.horizon_s is None
    assert held_out.mean() == pytest.approx(0.3) and not held_out[:200].any()
    assert list(data.starts[0]) == [0]


def test_closed_loop_logs_are_compared_over_restart_windows():
    n = 1000
    u = binary(n, 4)
    log = make_log(
        [RunData(1, np.arange(n) / FS, u, u.copy(), np.cumsum(u) / FS)], {"loop": "closed, PD"}
    )
    data = prepare(log)
    step = int(DEFAULT_HORIZON_S * FS)
    assert data.horizon_s == DEFAULT_HORIZON_S and list(data.starts[0]) == list(
        range(0, n, step)
    )
    assert "restarted" in data.comparison


def test_short_runs_and_no_motion_are_identification_errors():
    with pytest.raises(IdentificationError, match="samples"):
        prepare(make_log([RunData(1, np.arange(10) / FS, np.zeros(10), np.zeros(10))]))
    with pytest.raises(IdentificationError, match="does not move"):
        prepare(make_log([RunData(1, np.arange(100) / FS, np.ones(100), np.zeros(100))]))


def test_gap_is_rms_error_over_std_of_measured_velocity():
    params = PlantParams()
    data = prepare(plant_log(params))
    e = [np.full(len(r.v), 0.01) for r in data.segments]
    v_sim = [r.v + d for r, d in zip(data.segments, e, strict=True)]
    expected = 100 * 0.01 / np.std(data.cat("v"))
    assert gap_percent(data, v_sim) == pytest.approx(expected)


def test_noise_floor_estimates_white_sensor_noise():
    params = PlantParams(noise=0.02)
    data = prepare(plant_log(params))
    expected = 100 * 0.02 / np.std(data.cat("v"))
    assert noise_floor_percent(data) == pytest.approx(expected, rel=0.15)


def test_noise_floor_counts_the_rounding_of_a_velocity_reported_in_whole_steps():
    """A drive reporting velocity in whole rpm: second differences of the stepped velocity are
    mostly 0, yet its rounding is noise of step/sqrt(12) the model cannot reproduce."""
    rpm = 2 * math.pi / 60
    log = plant_log(PlantParams(noise=0.0), n=4000)
    run = log.runs[0]
    stepped = RunData(run.run, run.t, run.u, rpm * np.round(run.v / rpm), run.x)
    data = prepare(make_log([stepped]))
    assert data.v_step == pytest.approx(rpm)
    expected = 100 * rpm / math.sqrt(12) / np.std(data.cat("v"))
    assert noise_floor_percent(data) == pytest.approx(expected, rel=0.05)
    smooth = prepare(make_log([run]))
    assert smooth.v_step == 0.0 and noise_floor_percent(smooth) < 0.2 * expected


def test_the_true_base_model_leaves_only_the_noise():
    params = PlantParams(noise=0.01)
    data = prepare(plant_log(params))
    truth = Candidate({"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4})
    gap = gap_percent(data, simulate(data, truth))
    assert gap == pytest.approx(noise_floor_percent(data), rel=0.15)


def test_refit_recovers_the_base_model_from_a_poor_start():
    data = prepare(plant_log(PlantParams(noise=0.005)))
    start = Candidate({"M": 0.07, "B": 1.4, "coulomb_pos": 0.3, "coulomb_neg": 0.6})
    fit = refit(data, start, bounds={})
    b = fit.candidate.base
    assert b["M"] == pytest.approx(0.1, rel=0.02) and b["B"] == pytest.approx(1.0, rel=0.02)
    assert b["coulomb_pos"] == pytest.approx(0.5, rel=0.05) and b["coulomb_neg"] == pytest.approx(
        0.4, rel=0.05
    )


def test_signatures_locate_a_position_periodic_residual():
    data = prepare(plant_log(PlantParams()))
    v_sim = [r.v - 0.2 * np.sin(2 * math.pi * r.x / 0.1) for r in data.segments]
    sig = compute_signatures(data, v_sim)
    assert sig.vs_position.eta2 > 0.5 > sig.vs_velocity.eta2
    assert sig.acf_max > sig.band95  # a structured residual is not white
    text = sig.findings()
    where = {
        k: next(i for i, f in enumerate(text) if f.startswith(k)) for k in ("position", "velocity")
    }
    assert where["position"] < where["velocity"]


def test_signatures_of_a_perfect_model_with_white_noise_are_white():
    data = prepare(plant_log(PlantParams(noise=0.02)))
    truth = Candidate({"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4})
    sig = compute_signatures(data, simulate(data, truth))
    assert sig.acf_max < 2 * sig.band95
    assert abs(sig.xcorr_peak) < 3 * sig.band95
    assert sig.vs_velocity.eta2 < 0.05 and sig.vs_position.eta2 < 0.05


def test_linear_approximation_pole_moves_with_amplitude_for_friction():
    data = prepare(plant_log(PlantParams()))
    sig = compute_signatures(data, [r.v for r in data.segments])
    a, b = sig.linear
    # Coulomb friction weighs less at run 2's larger amplitude: the DC gain rises.
    assert b.gain_measured > a.gain_measured
    assert a.gain_measured == pytest.approx(a.gain_simulated)


def test_motion_in_one_direction_only_is_diagnosed_without_inventing_effects():
    from servobench.bench.diagnose.workflow import diagnose

    rng = np.random.default_rng(0)
    n = 1000
    u = np.abs(np.repeat(rng.normal(2.0, 1.0, n // 50), 50)) + 0.6  # always pushes forwards
    runs = []
    for number in (1, 2):
        v, x = plant_simulate(
            u * number, FS, PlantParams(noise=0.005), np.random.default_rng(number)
        )
        runs.append(RunData(number, np.arange(n) / FS, u * number, v, x))
    d = diagnose(make_log(runs))
    assert d.effects == () and d.base["M"] == pytest.approx(0.1, rel=0.02)


def test_an_offset_and_shifted_coulomb_levels_are_one_family_the_simulator_cannot_tell_apart():
    """Every member of the family the diagnosis reports moves the simulated axis exactly alike,
    the ends of its offset range included; a wider shift is another plant."""
    from servobench.bench.diagnose.families import offset_family

    base = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.3}
    family = offset_family(base, {"offset": {"offset": 0.1}}, "N")
    assert family.parameters == ("offset", "coulomb_pos", "coulomb_neg")
    assert (family.net_pos, family.net_neg) == pytest.approx((0.4, 0.4))
    assert "one family" in family.sentence and "0.1 N" in family.sentence
    u = binary(1000, 9, 1.5)

    def velocity(offset: float) -> np.ndarray:
        s = offset - 0.1
        p = PlantParams(  # at the ends of the range a level reaches zero
            M=0.1,
            B=1.0,
            coulomb_pos=round(0.5 + s, 12),
            coulomb_neg=round(0.3 - s, 12),
            effects={"offset": {"offset": offset}},
        )
        return plant_simulate(u, FS, p, np.random.default_rng(0))[0]

    reference = velocity(0.1)
    lo, hi = family.offset_range
    for offset in (lo, 0.0, 0.25, hi):
        np.testing.assert_allclose(velocity(offset), reference, atol=1e-9)
    with pytest.raises(Exception, match="coulomb"):
        velocity(hi + 0.05)  # beyond the range a Coulomb level would be negative


def test_unequal_coulomb_levels_are_reported_as_a_family_equal_ones_are_not():
    from servobench.bench.diagnose.families import offset_family

    equal = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.45}
    assert offset_family(equal, {}, "N") is None
    family = offset_family({**equal, "coulomb_neg": 0.2}, {}, "N")
    assert family.offset_range == pytest.approx((-0.5, 0.2))
    assert "equal levels of 0.35 N plus a constant force of -0.15 N" in family.sentence


@pytest.mark.parametrize(
    ("seed", "shape", "knots"),
    [(1, "line", (2, 2)), (2, "line", (2, 2)), (1, "wiggle", (5, 8)), (3, "wiggle", (5, 8))],
)
def test_position_friction_s_knot_count_is_chosen_on_held_out_samples(seed, shape, knots, tmp_path):
    """A friction that rises linearly along the travel gets the two knots of a line; one that
    rises and falls through six knots gets about as many. Seeds 1 and 2 of the line drew six
    and seven knots under a rule that kept any knot gaining 2% of the held-out error."""
    from dataclasses import replace

    from servobench.bench.diagnose.screening import screen_input
    from servobench.bench.log.io import read_log
    from servobench.bench.testing.hidden_effects import (
        position_friction_params,
        random_case,
        write_case_log,
    )
    from servobench.sim_backend.physics.effects import position_friction

    rng = np.random.default_rng(seed)
    case = random_case("position_friction", rng)
    p, b = case.effects["position_friction"], case.params
    fc = 0.5 * (b.coulomb_pos + b.coulomb_neg)
    values = [0.0, fc] if shape == "line" else fc * np.array([0, 0.8, -0.1, 0.9, 0.0, 1.0])
    effects = {"position_friction": position_friction_params(p["x_from"], p["x_to"], values)}
    case = replace(case, params=b.with_changes(effects=effects), effects=effects)
    data = prepare(read_log(write_case_log(case, tmp_path / "log.csv", rng)))
    truth = Candidate({"M": b.M, "B": b.B, "coulomb_pos": b.coulomb_pos, "coulomb_neg": b.coulomb_neg})
    s = position_friction.screen(screen_input(data, truth, simulate(data, truth)))
    assert knots[0] <= s.guess["knots"] <= knots[1]
    assert all(a["knots"] > s.guess["knots"] for a in s.alternatives)  # more go to simulation


def test_identify_and_diagnose_refuse_and_accept_motion_by_one_rule():
    """One motion rule (:func:`servobench.bench.identify.motion.require_motion`): a slow sine
    whose rms is 1.2 noise sigmas is motion to both (diagnose's own rule, a spread of 3
    sigmas, refused it while identify took it), and noise alone is refused by both with
    the same words."""
    from servobench.bench.identify.dataset import prepare as identify_prepare
    from servobench.bench.identify.motion import require_motion

    rng = np.random.default_rng(5)
    n = 4000
    t = np.arange(n) / FS
    u = 0.3 * np.sign(np.sin(2 * np.pi * 0.5 * t))
    slow = 0.012 * math.sqrt(2) * np.sin(2 * np.pi * 0.5 * t - 0.3)
    moving = make_log([RunData(1, t, u, slow + rng.normal(0, 0.01, n))])
    still = make_log([RunData(1, t, u, rng.normal(0, 0.01, n))])
    require_motion([r.v for r in moving.runs])  # identify's check: moves
    prepare(moving)  # diagnose: moves too
    words = []
    for check in (lambda: require_motion([r.v for r in identify_prepare(still).segments]), lambda: prepare(still)):
        with pytest.raises(IdentificationError, match="no motion above the sensor noise") as err:
            check()
        words.append(str(err.value).split(" in ")[0])
    assert words[0] == words[1]


def test_backlash_screens_a_position_quantised_coarser_than_a_samples_travel():
    """A slow axis read by a coarse encoder: most samples repeat the last position, so the
    median step is nil. The screen once tried gaps from 0 (numpy's geomspace refuses it)."""
    from servobench.bench.diagnose.screening import screen_input
    from servobench.sim_backend.physics.effects import backlash

    params = PlantParams(M=0.2, B=2.0, coulomb_pos=0.4, coulomb_neg=0.3)
    log = plant_log(params)
    runs = [RunData(r.run, r.t, r.u, r.v, np.round(r.x / 0.01) * 0.01) for r in log.runs]
    data = prepare(make_log(runs))
    steps = np.concatenate([np.abs(np.diff(s.position)) for s in data.segments])
    assert np.median(steps) == 0.0  # the case: a nil median step
    truth = Candidate({"M": 0.2, "B": 2.0, "coulomb_pos": 0.4, "coulomb_neg": 0.3})
    s = backlash.screen(screen_input(data, truth, simulate(data, truth)))
    assert s.guess["gap"] > 0 and all(a["gap"] > 0 for a in s.alternatives)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_cogging_periodogram_peak_is_the_direct_sine_and_cosine_one(seed):
    """The screen's periodogram (block products of exponentials) picks the frequency the direct
    sum of sines and cosines picks, on an irregular travel with a line buried in noise."""
    from servobench.sim_backend.physics.effects.cogging import _peak

    rng = np.random.default_rng(seed)
    x = np.cumsum(rng.uniform(0.0, 1e-3, 3000))
    e = 0.3 * np.sin(2 * np.pi * x / rng.uniform(0.01, 0.1) + 1.0) + rng.normal(size=x.size)
    k_lo, k_hi, count = 2 * np.pi * 3 / np.ptp(x), 2 * np.pi / 6e-3, 700
    ks = np.linspace(k_lo, k_hi, count)
    s, c = np.sin(ks[:, None] * x), np.cos(ks[:, None] * x)
    power = (s @ e) ** 2 / np.sum(s * s, axis=1) + (c @ e) ** 2 / np.sum(c * c, axis=1)
    assert _peak(k_lo, k_hi, count, x, e) == ks[np.argmax(power)]


class _PhaseError:
    """A training error whose cost is the distance of the cogging phase from ``best`` [rad]."""

    def __init__(self, best: float) -> None:
        self.best = best

    def residuals(self, cands):
        return [np.array([c.effects["cogging"]["phase"] - self.best, c.effects["cogging"]["amp"] - 1.0])
                for c in cands]  # fmt: skip


def test_the_coarse_scan_moves_an_angle_by_offsets_and_an_amplitude_by_factors():
    from servobench.bench.diagnose.refit import ANGLE_COARSE, COARSE, _line_search

    start = Candidate({"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4},
                      {"cogging": {"amp": 0.8, "period": 0.2, "phase": 0.0}})  # fmt: skip
    error = _PhaseError(best=0.12)
    cost = float(np.sum(error.residuals([start])[0] ** 2))
    bounds = {"cogging": {"amp": (0.0, 4.0), "phase": (-math.pi, math.pi)}}
    found, found_cost = _line_search(
        error, start, cost, {"cogging": ("phase", "amp")}, COARSE, bounds, ANGLE_COARSE
    )
    # a phase at 0 times any factor stays 0: only an offset reaches the well 0.12 rad away
    assert found.effects["cogging"]["phase"] == pytest.approx(0.12)
    assert found.effects["cogging"]["amp"] == pytest.approx(0.8 * 1.25)  # the factor that reaches 1.0
    assert found_cost < cost
