"""The friction-aware joint estimator against analytic (simulated) cases."""

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from servobench.bench.identify.auto import identify
from servobench.bench.identify.dataset import prepare
from servobench.bench.identify.joint import identify_joint
from servobench.bench.log.io import ExperimentLog, RunData
from servobench.bench.procedure.excitation import make_design
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.errors import IdentificationError
from servobench.sim_backend.physics.plant import PlantParams, PlantState, simulate_coulomb

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


def _params(model):
    return [model.M, model.B, model.coulomb_pos, model.coulomb_neg]


@pytest.mark.parametrize("amplitude", [1.0, 150.0])
def test_noise_free_joint_is_exact_at_low_and_high_amplitude(amplitude):
    log = simulate_experiment(TRUE, make_design(amplitude))
    r = identify(log, "joint")
    assert r.method == "joint"
    assert_allclose(_params(r.model), [0.1, 1.0, 0.5, 0.4], rtol=1e-3)
    assert_allclose([r.model.pole, r.model.dc_gain], [-10.0, 1.0], rtol=1e-3)
    assert r.fit_percent > 99.9


def test_noisy_joint_is_unbiased_within_its_uncertainty():
    sigma = 0.01
    log = simulate_experiment(TRUE.with_changes(noise=sigma, seed=7), make_design(1.0))
    est = identify_joint(prepare(log))
    assert est.estimator == "output-error"
    assert est.noise_std == pytest.approx(sigma, rel=0.1)
    for key, true in (("M", 0.1), ("B", 1.0), ("coulomb_pos", 0.5), ("coulomb_neg", 0.4)):
        value = getattr(est.model, key)
        assert 0 < est.std[key] < 0.02 * true
        assert abs(value - true) < 4 * est.std[key], key


def test_position_only_open_loop_log():
    log = simulate_experiment(TRUE, make_design(1.0, period_s=2.0, periods=3), with_velocity=False)
    r = identify(log, "joint")
    assert "output-error" in r.estimator
    assert_allclose(_params(r.model), [0.1, 1.0, 0.5, 0.4], rtol=5e-3)


def _closed_loop_run(noise=0.0, jitter=0.0, seed=0):
    """A PI velocity loop tracking a random step reference; exact plant between samples."""
    rng = np.random.default_rng(seed)
    n = 6000
    dt = 1e-3
    dts = dt * (1 + jitter * rng.uniform(-1, 1, n - 1))
    ref = np.repeat(rng.uniform(-2, 2, n // 300), 300)
    v = np.zeros(n)
    u = np.zeros(n)
    state = PlantState()
    integ = 0.0
    for k in range(n):
        v[k] = state.v
        meas = state.v + (rng.normal(0, noise) if noise else 0.0)
        e = ref[k] - meas
        integ += e * dt
        u[k] = 2.0 * e + 5.0 * integ
        if k < n - 1:
            _, _, state = simulate_coulomb(np.array([u[k]]), dts[k], TRUE, state)
    t = np.concatenate(([0.0], np.cumsum(dts)))
    v_meas = v + (rng.normal(0, noise, n) if noise else 0.0)
    return ExperimentLog((RunData(1, t, u, v_meas),), {"fs": "1000", "loop": "closed"}, 1000.0)


def test_single_run_closed_loop_arbitrary_excitation():
    r = identify(_closed_loop_run(), "auto")
    assert r.method == "joint"
    assert "sidbe cannot run" in r.selection
    assert_allclose(_params(r.model), [0.1, 1.0, 0.5, 0.4], rtol=1e-3)


def test_irregular_time_stamps_use_per_sample_intervals():
    log = _closed_loop_run(jitter=0.2, seed=3)
    data = prepare(log)
    assert data.jittered
    r = identify(log, "joint")
    assert any("irregular" in n for n in r.notes)
    assert_allclose(_params(r.model), [0.1, 1.0, 0.5, 0.4], rtol=1e-3)
    # a nominal-dt fit of the same data is visibly worse: the jitter matters
    assert r.fit_percent > 99.9


def test_no_motion_is_an_identification_error():
    log = simulate_experiment(TRUE, make_design(0.3))  # below both friction levels: never moves
    with pytest.raises(IdentificationError, match="no motion"):
        identify(log, "joint")


def test_noise_only_motion_is_an_identification_error():
    log = simulate_experiment(TRUE.with_changes(noise=0.01, seed=1), make_design(0.3))
    with pytest.raises(IdentificationError, match="motion"):
        identify(log, "joint")


def test_one_direction_only_leaves_the_other_level_undetermined():
    d = make_design(1.0)
    log = simulate_experiment(TRUE, d)
    runs = tuple(
        RunData(r.run, r.t, np.abs(r.u), r.v, r.x) for r in log.runs
    )  # u >= 0: never moves backwards
    pos_only = ExperimentLog(runs, {"fs": "1000"}, 1000.0)
    runs_sim = []
    for r in runs:
        v, x, _ = simulate_coulomb(r.u, 1e-3, TRUE)
        runs_sim.append(RunData(r.run, r.t, r.u, v, x))
    r = identify(ExperimentLog(tuple(runs_sim), pos_only.metadata, 1000.0), "joint")
    assert_allclose([r.model.M, r.model.B, r.model.coulomb_pos], [0.1, 1.0, 0.5], rtol=1e-3)
    assert r.model.coulomb_neg == 0.0
    assert math.isfinite(r.fit_percent)


def test_a_served_serial_log_whose_pairs_hold_no_switch_takes_its_delay_from_the_simulation():
    """``tests/data/served_serial_1ms_blind_pairs.csv``: a default ``sidbe`` against a served
    ODrive-protocol drive with a 1 ms tick of its own (plant M 0.01, B 1, Coulomb 0.5 / 0.4),
    at 200 Hz on a machine with three busy processes. Every command switch reverses the axis
    within its interval, so no sample pair holds one, and the pair scan's minimum over delays is
    the noise's: it took 0.9 cycles there, the instrumental fit then diverged (a traceback from
    ``math.exp`` overflowing; with that caught, a mass of 3e-8 and a fit of 79 %). The delay now
    comes from the simulation, as where the pairs show no curvature."""
    result = _served_plant_within_1_percent("served_serial_1ms_blind_pairs.csv")
    assert 0.0 <= result.model.delay_s <= 1e-3  # the drive's record: 0.76 ms over all commands


def test_a_served_serial_log_whose_constant_delay_overshoots_its_tick_finds_the_tick():
    """``tests/data/served_serial_2ms_tick_below_delay.csv``: a default ``sidbe`` against a served
    ODrive-protocol drive with a 2 ms tick of its own (plant M 0.01, B 1, Coulomb 0.5 / 0.4), at
    200 Hz. The rows' delays differ (the command a request ahead of its query), and the constant
    delay identified overshot the tick: 2.40 +- 0.13 ms, where the drive's record shows a mean of
    1.66 ms over the changed commands. Only ticks from the delay on were tried, no grid was
    located, and the model came out 5.1 % off with a fit of 95.7 %. The nominal tick below the
    delay is tried too now."""
    result = _served_plant_within_1_percent("served_serial_2ms_tick_below_delay.csv")
    assert result.model.delay_s == pytest.approx(1.661e-3, abs=0.2e-3)  # the tick's tenth


def test_a_served_serial_log_whose_rows_act_apart_from_their_samples_predicts_its_error():
    """``tests/data/served_serial_0125ms_tick_split_requests.csv``: a default ``sidbe`` (two
    periods of 2 s) against a served ODrive-protocol drive with a 0.125 ms tick of its own, at
    200 Hz. The command and the query are two requests: each command acts at the drive's tick
    after it arrives, each query returns the tick before, so the rows' delays spread over two
    ticks (the drive's record: -0.375 to -0.125 ms). No grid is located at this tick and the
    model holds one delay: M -0.12 %, B -0.18 %, Coulomb +0.14 % / +0.29 %. The timing figure's
    draws moved each row's instant with its command; they predicted 0.21 % for that 0.29 %. Each
    draw now moves where the command acts apart from its row's sample too, by the scatter read at
    the command's changes (0.062 ms; the scatter read against the acceleration, 0.095 ms, which
    the actions took before, predicted 0.33 % at one sigma, 0.66 % at two): each parameter within
    two of its 1 sigma, the worst within the two-sigma bound, which is no wider than 0.6 %."""
    result = _served_plant_within_1_percent("served_serial_0125ms_tick_split_requests.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    errors = {k: abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items()}
    worst = max(errors.values())
    assert 0.1 < worst < 1.0  # the log shows the rows' delay spread
    timing = result.timing
    assert timing is not None and timing.action_scatter_s == pytest.approx(0.06e-3, rel=0.3)
    assert all(errors[k] <= 2.0 * timing.model_error_pct[k] for k in true), (errors, timing.model_error_pct)
    assert worst <= timing.model_error_bound_pct < 0.6
    assert result.to_json()["timing"]["action_scatter_s"] == pytest.approx(timing.action_scatter_s)


def test_a_served_log_whose_reads_straddle_the_ticks_is_phased_by_its_placed_pairs():
    """``tests/data/served_modbus_tcp_1ms_tick_stalled_host.csv``: a default ``sidbe`` (two
    periods of 2 s) against a served Modbus TCP drive with a 1 ms tick of its own and no time
    stamp, read at 1 kHz by a host stopped for 30-150 ms every 0.5-1.5 s under two busy processes
    (301 missed cycles; half the reads return the tick before). The grid alone read run 1's phase
    where the pairs could not place the reads near a tick: fit 98.86 %, Coulomb 0.76 % off. Read
    again by the pairs of the model identified on it, the fit is 99.999 %."""
    result = _served_plant_within_1_percent("served_modbus_tcp_1ms_tick_stalled_host.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert worst < 0.05
    assert result.fit_percent > 99.99
    assert result.model.delay_s == pytest.approx(1e-3, abs=0.01e-3)  # the drive's record: 1 ms
    _posterior_prediction_is_tight(result, worst)


def _posterior_prediction_is_tight(result, worst: float) -> None:
    """Reads the pairs placed on the grid: the timing figure's draws come from the pairs'
    posterior, and its prediction covers the error within a tenth of the accuracy. Draws that
    placed each read anywhere in its bracket and let the pairs place it again moved the brackets
    themselves: on the two logs that place reads by pairs here, the delay by 0.009 and 0.019 ms,
    and M, through the delay held that far off, predicted 0.16 % and 0.30 % at two sigma for
    models within 0.0001 %."""
    timing = result.timing
    assert "posterior" in timing.method, timing.method
    assert worst <= timing.model_error_bound_pct <= 0.1, (worst, timing.model_error_pct)
    assert abs(result.model.delay_s - 1e-3) <= 3.0 * result.std["delay_s"] + 1e-9


def test_reads_the_pairs_place_as_the_grid_does_are_drawn_from_the_pairs_posterior():
    """``tests/data/served_modbus_rtu_1ms_busy_nostamp_grid_tie.csv``: the suite's default ``sidbe``
    against a served Modbus RTU drive without its time stamp, a 1 ms tick of its own, at 50 Hz
    beside two busy processes. The grid alone fits 100.000 %, the reads placed by the model's
    pairs 99.999 %: a tie. The pairs' placement was taken only where it fitted better, so the
    timing figure's draws placed each read anywhere in its bracket of +-1.3 ms: the delay moved
    0.22 ms over the draws and M, through the delay held that far off, predicted 1.92 % at two
    sigma for a model 0.005 % off ("not within accuracy"). Taken on a tie, the pairs place the
    reads and the draws come from their posterior: 0.58 %, within accuracy, the delay
    1.0 ms +- 0.005 ms. (On eight more such logs at 0.25 ms: 1.03-1.15 % -> 0.59-0.82 %.)"""
    result = _served_plant_within_1_percent("served_modbus_rtu_1ms_busy_nostamp_grid_tie.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    timing = result.timing
    assert "posterior" in timing.method, timing.method
    assert worst <= 0.01, worst
    assert worst <= timing.model_error_bound_pct <= 1.0 and timing.within_accuracy, timing.model_error_pct
    assert abs(result.model.delay_s - 1e-3) <= max(0.05e-3, 3.0 * result.std["delay_s"])
    assert result.std["delay_s"] <= 0.02e-3


@pytest.mark.parametrize(("name", "record_s", "before_pct"), [
    ("served_serial_2ms_tick_below_delay.csv", 1.661e-3, 5.3),
    ("served_serial_1ms_tick_delay_spread.csv", 0.4915e-3, 3.9),
])  # fmt: skip
def test_reads_in_doubt_behind_a_command_lead_are_drawn_by_their_odds(name, record_s, before_pct):
    """Served ODrive-protocol logs (a command sent a request ahead of its query) whose reads were
    placed on a located grid by the model's simulation. The timing figure's draws placed each
    read anywhere in its bracket, by the grid alone, and held the delay as far apart as the
    draws moved it: the delay, the mean of the rows' placed delays over the command changes,
    moved with the few reads in doubt while the actions stayed, and held apart, every action
    moved with it, it predicted 5.3 % and 3.9 % at two sigma for models 0.00002 % and 0.06 % off
    ("not within accuracy" for exact models). Each draw now places every read in doubt by its
    odds under the model, and the draws hold the timing's whole effect."""
    result = _served_plant_within_1_percent(name)
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    timing = result.timing
    assert "odds under the model" in timing.method and "held" not in timing.method, timing.method
    assert worst <= timing.model_error_bound_pct <= 1.0 < before_pct, (worst, timing.model_error_pct)
    assert timing.within_accuracy
    assert abs(result.model.delay_s - record_s) <= 3.0 * result.std["delay_s"]


def test_the_delays_stated_sigma_holds_its_timing_share():
    """``tests/data/served_serial_1ms_tick_delay_spread.csv``: a fresh-clone suite's default
    ``sidbe`` (two periods of 2 s) against a served ODrive-protocol drive with a 1 ms tick, at
    200 Hz, no stamps (the drive's record: the commands that changed the value acted 0.4915 ms
    after their samples on average, each 0 or 1 ms). The delay came out 0.552 ms with a fit's
    1 sigma of 0.0006 ms: a hundred sigma off. The stated sigma now holds the delay's spread over
    the timing figure's draws too (0.028 ms)."""
    result = _served_plant_within_1_percent("served_serial_1ms_tick_delay_spread.csv")
    error = abs(result.model.delay_s - 0.4915e-3)
    assert error > 10.0 * result.timing.delay_std_s  # the fit's sigma alone does not hold
    assert error <= 3.0 * result.std["delay_s"]
    assert result.std["delay_s"] == pytest.approx(result.timing.delay_error_s)
    assert result.timing.to_json()["delay_error_s"] == pytest.approx(result.std["delay_s"])


def test_a_served_rtu_log_whose_transients_carry_timing_errors_weighs_them_by_their_timing():
    """``tests/data/served_modbus_rtu_0125ms_busy_nostamp.csv``: a default ``sidbe`` (4 periods
    of 4 s) against a served Modbus RTU drive without its time-stamp register, a 0.125 ms tick
    of its own, at 50 Hz under two busy processes. The emulated wire (a pty) delays a few
    exchanges by milliseconds: the intervals' timing errors are 0.04 ms at the median and one
    of 140 in the transients is 1.6 ms off. Weighted equally, the output-error samples gave M
    2.74 % off and the delay 0.73 +- 0.41 ms against the record's 0.125 ms (predicted 3.7 %).
    Weighted by the share of their variance that is velocity noise, the timing errors of the
    intervals before them carried as the plant remembers them: within 0.05 %. The two weightings
    part by 2.7 % on this log, and the timing figure counts that: it is not within accuracy."""
    from servobench.bench.identify.timing import METHOD_WEIGHTING

    result = _served_plant_within_1_percent("served_modbus_rtu_0125ms_busy_nostamp.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert worst < 0.05
    assert abs(result.model.delay_s - 0.125e-3) <= 0.05e-3  # the bound against the record
    timing = result.timing
    assert timing is not None and METHOD_WEIGHTING in timing.method
    assert timing.model_error_max_pct > 1.0 and not timing.within_accuracy


def test_a_delay_the_timing_misleads_moves_the_plant_along_the_fits_trade_and_the_figure_counts_it():
    """``tests/data/served_modbus_rtu_025ms_busy_nostamp_delay_trade.csv``: a default ``sidbe``
    against a served Modbus RTU drive without its time stamp, a 0.25 ms tick of its own, under
    two busy processes (no tick grid located at 50 Hz). The delay came out 0.277 +- 0.020 ms
    against the record's 0.25 and M 0.075 % small along the fit's trade between the delay and
    the time constant; the draws and the model's own sigma predicted 0.072 % at two sigma.
    Held one timing sigma of the delay either side, the refit moves M by that trade, and the
    figure counts it: the bound covers the error."""
    from servobench.bench.identify.timing import METHOD_DELAY_HELD

    result = _served_plant_within_1_percent("served_modbus_rtu_025ms_busy_nostamp_delay_trade.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    timing = result.timing
    assert timing is not None and METHOD_DELAY_HELD in timing.method
    assert abs(result.model.delay_s - 0.25e-3) <= 0.05e-3  # the bound against the record
    assert worst <= timing.model_error_bound_pct, (worst, timing.model_error_pct)


def test_a_delay_between_the_whole_ticks_of_its_grid_is_uncertain_by_its_distance_to_them():
    """On a located grid where one request carries command and sample, each command acts a whole
    number of ticks after its sample; a model acting between two holds reads on the wrong tick,
    which neither the fit's sigma nor the draws see. A fresh-clone suite gave served Modbus RTU at
    a 0.25 ms tick without stamps, host stalls of 58 ms, the delay 0.413 ms against the record's
    0.25 with a stated sigma of 0.041 ms (4 sigma off). Its distance to the nearer whole tick count
    (0.087 ms) now joins the delay's timing share, and a delay short of one tick is its
    distance to one tick. On a grid's exact model the term is nothing, and the method names it."""
    from servobench.bench.identify.drive_grid import off_grid_s
    from servobench.bench.identify.timing import METHOD_OFF_GRID

    assert off_grid_s(0.413e-3, 0.25e-3) == pytest.approx(0.087e-3)
    assert off_grid_s(0.1e-3, 0.25e-3) == pytest.approx(0.15e-3)  # one tick at least
    assert off_grid_s(2.0e-3, 1e-3) == 0.0
    stated = math.hypot(0.032e-3, 0.026e-3)  # that run's fit sigma and its draws' share
    assert abs(0.413e-3 - 0.25e-3) > 3.0 * stated
    assert abs(0.413e-3 - 0.25e-3) <= 3.0 * math.hypot(stated, off_grid_s(0.413e-3, 0.25e-3))
    result = _served_plant_within_1_percent("served_modbus_tcp_1ms_tick_stalled_host.csv")
    assert METHOD_OFF_GRID in result.timing.method
    # held at the grid's tick; the term holds the free delay's distance from it
    assert result.model.delay_s == pytest.approx(1e-3, rel=1e-4)


def test_on_a_located_grid_the_delay_is_held_at_its_whole_ticks():
    """``tests/data/served_modbus_rtu_025ms_idle_nostamp_free_delay.csv``: a suite's default
    ``sidbe`` against a served Modbus RTU drive without its time stamp, a 0.25 ms tick of its own,
    idle, at 50 Hz. Its 0.25 ms grid was located, and the delay left free on it came out
    0.305 +- 0.067 ms against the record's 0.25 (beyond the issue's 0.05 ms), M 0.095 % small
    along the trade between the two. One request carrying command and sample, each command acts
    a whole tick after its sample on that grid: held there, the delay is the record's and M
    0.0065 % off; the free delay's departure stays in the delay's stated sigma, and the note says both."""
    result = _served_plant_within_1_percent("served_modbus_rtu_025ms_idle_nostamp_free_delay.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert any("control tick (0.25 ms)" in note for note in result.notes), result.notes
    assert result.model.delay_s == pytest.approx(0.25e-3, rel=1e-4)  # the grid's tick, drift 12.5 ppm
    assert worst <= 0.02, worst
    assert result.std["delay_s"] >= 0.05e-3  # the free delay's 0.055 ms from the tick
    held = [n for n in result.notes if n.startswith("the action delay held there")]
    assert held == ["the action delay held there, 1 tick after the sample (0.25 ms; left free the log "
                    "gives 0.3047 ms)"]
    assert worst <= result.timing.model_error_bound_pct


def test_a_switch_sent_in_an_exchange_the_host_stalled_in_bends_no_model():
    """``tests/data/served_modbus_rtu_025ms_stalled_switch.csv``: default ``sidbe`` (the suite's
    short excitation) against a served Modbus RTU drive without its time stamp, a 0.25 ms tick of
    its own, 50 Hz, beside two busy processes and a host stopped for 30-150 ms every 0.5-1.5 s.
    One stop fell in the exchange of a switch (bracket +-34 ms): the request went out somewhere in
    it, so where that command acted is unknown, and the samples after it were the only weight the
    output error saw beside its transients' (each weighted down by its own timing). The model
    came out M 46 % off, the delay 7.9 ms, fit 97.5 %, where the true model verifies 99.90 %.
    The command's uncertain instant now weighs the samples after it, and the verification leaves
    them out."""
    from pathlib import Path

    from servobench.bench.identify.dataset import prepare
    from servobench.bench.log.io import read_log

    name = "served_modbus_rtu_025ms_stalled_switch.csv"
    data = prepare(read_log(Path(__file__).parent / "data" / name))
    exposed = sum(int(s.after_stalled_commands(data.dt_s, 0.01, 1.0).sum()) for s in data.segments)
    assert exposed >= 1  # the sample after the stalled switch
    result = _served_plant_within_1_percent(name)
    assert abs(result.model.M / 0.01 - 1.0) <= 0.001, result.model
    assert abs(result.model.delay_s - 0.25e-3) <= 0.05e-3, result.model.delay_s
    assert result.fit_percent >= 99.9
    assert result.timing.within_accuracy


def test_a_stalled_switch_leaves_the_drive_grid_to_be_found():
    """``tests/data/served_modbus_rtu_1ms_stalled_switch.csv``: as above at a 1 ms tick. A stop
    in one switch's exchange (bracket +-3.9 ms against the log's +-1.2 ms) left the sample after
    it 0.05 off under any grid, so run 1's 1 ms grid cut its simulation residual 1.15 times (run
    2's: 3e6 times) and no grid was kept: the delay 0.66 +- 0.34 ms against 1.0, fit 99.45 %, the
    prediction 2.4 % and "not within accuracy" for a model 0.03 % off. The grid is judged without
    the samples of stalled exchanges and those their commands may have moved: located, the model is
    exact and acts one tick after its sample."""
    result = _served_plant_within_1_percent("served_modbus_rtu_1ms_stalled_switch.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert any("control tick (1 ms) located" in note for note in result.notes), result.notes
    assert worst <= 0.01, worst
    assert abs(result.model.delay_s - 1e-3) <= 0.05e-3, result.model.delay_s
    assert result.fit_percent >= 99.9
    assert result.timing.within_accuracy and result.timing.model_error_bound_pct >= worst


def test_behind_a_command_lead_the_stalled_exchanges_bend_no_model():
    """``tests/data/served_serial_025ms_stalled_exchanges.csv``: default ``sidbe`` (4 periods of
    4 s) against a served ODrive serial drive, a 0.25 ms tick of its own, 200 Hz, idle. Each
    command goes ahead of its query, so the output error weighs its samples alike; two exchanges
    the host stalled in (one bracket +-2.8 ms) left the samples after them 0.1 off where every
    other sample sat within 1e-4 of the true model, and they bent M 0.18 % off and the delay to
    -0.010 ms against the drive's record of -0.0735 ms over its command changes. The samples of
    stalled exchanges, and those their commands may have moved, are left out of the fit."""
    result = _served_plant_within_1_percent("served_serial_025ms_stalled_exchanges.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert any("control tick (0.25 ms) located" in note for note in result.notes), result.notes
    assert any("left out of the output-error and verification fits" in note for note in result.notes), result.notes
    assert worst <= 0.05, worst
    assert abs(result.model.delay_s - (-0.0735e-3)) <= 0.05e-3, result.model.delay_s  # the bound
    assert result.timing.within_accuracy and result.timing.model_error_bound_pct >= worst


def test_reads_every_bracket_leaves_in_doubt_keep_their_tick_where_the_motion_cannot_tell():
    """``tests/data/served_serial_025ms_settled_change_reads.csv``: the suite's short ``sidbe``
    against a served ODrive serial drive, a 0.25 ms tick of its own, 200 Hz, idle. Its brackets
    (+-0.16 ms) leave every read in doubt between two ticks, so the reads not in doubt gave the
    model's residual scale no sample and it came out 0: under the constant-delay model each
    settled read, a command change's own among them, went to whichever tick its velocity matched
    in the last digits. 11 of run 2's 21 changes had their read moved a tick early (the true model
    moves one), and the delay, the mean over the changes of the ticks from sample to action, came
    out -0.036 ms against the drive's record of -0.116. The scale now comes from every read's
    nearer tick, and the reads it cannot decide take the share the decided ones show, nearest
    their tick boundary first."""
    result = _served_plant_within_1_percent("served_serial_025ms_settled_change_reads.csv")
    assert abs(result.model.delay_s - (-0.1163e-3)) <= 0.05e-3, result.model.delay_s  # the bound
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert result.timing.model_error_bound_pct >= worst


def test_a_log_stalled_throughout_keeps_its_samples_in_the_output_error():
    """Behind a command's lead the samples of stalled exchanges, and those their commands may have
    moved, are set aside from the output error; where that would leave fewer than half of a run,
    all are kept, as the timing's set-aside and the verification keep them."""
    from servobench.bench.identify.dataset import Segment
    from servobench.bench.identify.joint import MIN_KEPT_SHARE, _unstalled
    from servobench.bench.model.servo import ServoModel

    n, dt = 400, 5e-3
    t = np.arange(n) * dt
    u = np.where((np.arange(n) // 3) % 2 == 0, 1.0, -1.0)  # a switch every third row
    v = 0.5 * u
    model = ServoModel(M=0.01, B=1.0, coulomb_pos=0.1, coulomb_neg=0.1)
    few = np.full(n, 0.1e-3)
    few[[30, 150]] = 3e-3  # two stalled exchanges, both at a switch
    seg = Segment(1, t, u, v, 1.0 / dt, np.diff(t), t_unc=few)
    weight = _unstalled(seg, dt, model)
    assert 0 < np.count_nonzero(weight == 0.0) < (1 - MIN_KEPT_SHARE) * n  # set aside
    assert weight[30] == 0.0 and weight[150] == 0.0
    many = np.full(n, 0.1e-3)
    many[(np.arange(n) % 3 == 0) & (np.arange(n) % 2 == 0)] = 3e-3  # a stalled switch every sixth row
    seg = Segment(1, t, u, v, 1.0 / dt, np.diff(t), t_unc=many)
    assert np.count_nonzero(seg.stalled_samples(dt, model.M, model.B)) > (1 - MIN_KEPT_SHARE) * n
    assert _unstalled(seg, dt, model) == 1.0  # too many to judge without: all kept


def _served_plant_within_1_percent(name: str):
    """``identify`` on the kept served log ``tests/data/<name>`` (plant M 0.01, B 1, Coulomb
    0.5 / 0.4), checked within 1 % and a fit over 99 %."""
    from pathlib import Path

    from servobench.bench.log.io import read_log

    result = identify(read_log(Path(__file__).parent / "data" / name))
    for got, want in ((result.model.M, 0.01), (result.model.B, 1.0), (result.model.coulomb_pos, 0.5),
                      (result.model.coulomb_neg, 0.4)):  # fmt: skip
        assert got == pytest.approx(want, rel=0.01)
    assert result.fit_percent > 99.0
    return result


def test_a_grid_of_twice_the_tick_whose_model_acts_off_it_is_not_taken():
    """``tests/data/served_modbus_rtu_025ms_busy_nostamp_double_tick.csv``: a suite's default
    ``sidbe`` against a served Modbus RTU drive without its time stamp, a 0.25 ms tick of its own,
    under load, at 50 Hz. A 0.5 ms grid verified a little better than the 0.25 ms one (99.869 %
    against 99.859 %) with its model acting 0.265 ms after the sample, half a tick short of what
    that grid says; taken, it gave the delay 0.340 +- 0.022 ms against the record's 0.25, M 0.29 %
    off. Its model does not act on it, so it is not taken: the constant delay stays, with the
    sigma that says how loosely this rate knows it."""
    result = _served_plant_within_1_percent("served_modbus_rtu_025ms_busy_nostamp_double_tick.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert not any("control tick (0.5 ms)" in note for note in result.notes)
    delay, sigma = result.model.delay_s, result.std["delay_s"]
    assert abs(delay - 0.25e-3) <= max(0.05e-3, 2.0 * sigma), (delay, sigma)
    assert worst <= min(0.1, result.timing.model_error_bound_pct), worst


def test_reads_a_tick_off_that_bias_the_delay_still_find_the_drive_grid():
    """``tests/data/served_canopen_1ms_busy_nostamp_boundary_reads.csv``: default ``sidbe``
    (two periods of 2 s) against a served CANopen drive without a time-stamp object, a 1 ms
    tick of its own, beside two busy processes. The host's SYNC kept landing on the drive's tick
    boundary in the second run: its record shows 472 of 8028 reads answered from the tick of the
    read before. The constant delay the grid is looked for from came out 1.090 +- 0.029 ms, beyond
    a snap of 5 % of the 1 ms tick: no grid was tried, the fit was 96.7 % and M 0.12 % off. On
    the located grid the model is exact and acts one tick after its sample."""
    result = _served_plant_within_1_percent("served_canopen_1ms_busy_nostamp_boundary_reads.csv")
    true = {"M": 0.01, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    worst = max(abs(100.0 * (getattr(result.model, k) / v - 1.0)) for k, v in true.items())
    assert worst <= 0.01, worst
    assert result.fit_percent >= 99.9
    assert abs(result.model.delay_s - 1e-3) <= 0.05e-3, result.model.delay_s
    _posterior_prediction_is_tight(result, worst)


def _led_runs(action_sigma_s: float, seed: int = 3):
    """Two runs at 200 Hz of a binary command whose every change acts 0.2 ms before its row's
    instant (a command lead) and, on top, by a normal draw of ``action_sigma_s`` apart: the
    velocity stepped exactly (stick-slip) from event to event; brackets of +-0.5 ms."""
    from servobench.bench.identify.dataset import Dataset, Segment
    from servobench.bench.model.servo import ServoModel
    from servobench.sim_backend.physics.kernels import stick_slip_step

    rng = np.random.default_rng(seed)
    model = ServoModel(0.01, 1.0, 0.5, 0.4, delay_s=-0.2e-3)
    segments = []
    for run, amp in ((1, 1.0), (2, 0.9)):
        n = 1600
        t = np.arange(n) / 200.0
        u = amp * np.repeat(rng.choice([-1.0, 1.0], n // 10), 10)
        act = t + model.delay_s + rng.normal(0.0, action_sigma_s, n) if action_sigma_s else t + model.delay_s
        act[0] = t[0]
        events = sorted([(a, 1, j) for j, a in enumerate(act)] + [(s, 0, k) for k, s in enumerate(t)])
        v, now, force, out = 0.0, 0.0, u[0], np.zeros(n)
        for at, kind, k in events:
            v = stick_slip_step(v, force, at - now, 0.01, 1.0, 0.5, 0.4, 0.5, 0.4)
            now = at
            if kind:
                force = u[k]
            else:
                out[k] = v
        segments.append(Segment(run, t, u, out, 200.0, dt_s=np.diff(t), t_unc=np.full(n, 0.5e-3)))
    return Dataset(tuple(segments), 200.0, min_delay_s=-0.35e-3), model


@pytest.mark.parametrize("sigma_s", [0.0, 20e-6, 60e-6])
def test_the_actions_scatter_is_read_at_the_commands_changes(sigma_s):
    """:func:`~servobench.bench.identify.joint.action_scatter_s` reads how far each command's
    action strays (a binary command's every reversal crossing zero velocity inside its
    interval), where reading those intervals against their acceleration takes it for the
    sample's error and reads far more."""
    from servobench.bench.identify.joint import action_scatter_s, instant_scatter_s

    data, model = _led_runs(sigma_s)
    got = action_scatter_s(data, model)
    if sigma_s == 0:
        assert got < 1e-7
    else:
        assert got == pytest.approx(sigma_s, rel=0.25)
        assert instant_scatter_s(data, model) > 1.5 * got
