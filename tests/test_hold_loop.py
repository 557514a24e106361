"""Issue 11, the hold loop and the plan: gains, the predicted hold against independent peers, the travel plan."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import signal

from servobench.bench.model.servo import ServoModel
from servobench.bench.procedure.excitation import design_excitation, make_design
from servobench.bench.run.hold import (
    HoldController,
    HoldGains,
    design_hold,
    fit_hold_gains,
    simulate_hold,
)
from servobench.bench.run.travel import DESIGN_SHARE, TravelWindow, plan_closed_loop
from servobench.drivers.base import Limits
from servobench.drivers.registry import open_drive
from servobench.errors import UsageError

SIM = ServoModel(0.1, 1.0, 0.5, 0.4)
EMPS = ServoModel(95.1, 203.5, 17.2, 23.6)


@pytest.mark.parametrize("model", [SIM, EMPS], ids=["sim", "emps"])
@pytest.mark.parametrize("bandwidth_hz", [0.3, 2.0])
def test_design_places_the_closed_loop_poles(model, bandwidth_hz):
    g = design_hold(model.M, model.B, bandwidth_hz)
    w = 2 * math.pi * bandwidth_hz
    loop = [model.M, model.B + g.kd, g.kp, g.ki]  # M s^3 + (B + kd) s^2 + kp s + ki
    third, rest = np.polydiv(loop, [1.0, 2 * w, w * w])  # a critically damped pair at w ...
    assert np.max(np.abs(rest)) < 1e-9 * max(map(abs, loop))
    assert -third[1] / third[0] <= -w * (1 - 1e-9)  # ... and the third pole at or beyond -w
    assert all(p.real < 0 for p in np.roots(loop))


def test_the_predicted_hold_is_scipys_discrete_closed_loop():
    """Frictionless, the hold is linear: the drive-side loop on the ZOH plant, built here with
    scipy's discretisation (an independent integrator) and the loop's own equations."""
    model = ServoModel(0.2, 0.5, 0.0, 0.0)
    g = HoldGains(kp=8.0, ki=6.0, kd=0.3)
    dt = 1e-3
    u_exc = np.where((np.arange(3000) // 250) % 2 == 0, 0.4, -0.3)
    got = simulate_hold(model, HoldController(g, "drive", 0.0, dt), u_exc)
    # plant x' = v, M v' = -B v + u, sampled with zero-order hold by scipy
    ad, bd, *_ = signal.cont2discrete(
        (np.array([[0, 1], [0, -model.B / model.M]]), np.array([[0], [1 / model.M]]),
         np.eye(2), np.zeros((2, 1))), dt, method="zoh",
    )  # fmt: skip
    state, integral, xs = np.zeros(2), 0.0, []
    for uk in u_exc:
        xs.append(state[0])
        integral += -state[0] * dt
        u = uk + g.kp * -state[0] + g.ki * integral - g.kd * state[1]
        state = ad @ state + bd[:, 0] * u
    np.testing.assert_allclose(got.x, xs, rtol=0, atol=1e-12)


def test_the_predicted_hold_is_the_simulated_drive_held_by_the_host():
    """The predictor and the host's loop streamed through sim:// agree sample by sample."""
    from servobench.bench.run.closed import stream_closed_runs
    from servobench.bench.run.travel import ClosedLoopPlan

    design = make_design(1.0, period_s=1.0, periods=2, freqs_hz=(3.0, 5.0, 8.0, 13.0))
    controller = HoldController(design_hold(SIM.M, SIM.B, 0.6), "host", 0.0, 1e-3)
    u1 = design_excitation(design).u1
    predicted = simulate_hold(SIM, controller, u1)
    plan = ClosedLoopPlan(design, controller, 0.5, predicted.excursion(), SIM)
    from tempfile import TemporaryDirectory

    from servobench.bench.log.io import read_log

    with TemporaryDirectory() as d, open_drive("sim://?xmin=-0.5&xmax=0.5") as drive:
        stream_closed_runs(drive, [(1, u1)], 1000.0, f"{d}/log.csv", plan, settle_s=0.01)
        run = read_log(f"{d}/log.csv").run(1)
    np.testing.assert_allclose(run.x, predicted.x, atol=1e-9)
    np.testing.assert_allclose(run.u, predicted.u, atol=1e-9)
    np.testing.assert_allclose(run.u_exc, u1)


def test_fit_recovers_the_gains_of_a_drive_loop():
    rng = np.random.default_rng(3)
    e = np.cumsum(rng.normal(0, 1e-4, 4000))
    v = np.gradient(-e, 1e-3) + rng.normal(0, 1e-3, e.size)
    u_loop = 12.0 * e + 30.0 * np.cumsum(e) * 1e-3 - 0.4 * v + 0.05  # the integral started at 0.05
    got = fit_hold_gains(u_loop, e, v, 1e-3)
    assert (got.kp, got.ki, got.kd) == pytest.approx((12.0, 30.0, 0.4), rel=1e-6)
    assert fit_hold_gains(np.zeros(4000), e, v, 1e-3) is None  # no loop: nothing holds


def test_the_window():
    w = TravelWindow.of(Limits(min_position=-0.1, max_position=0.3))
    assert w.finite and w.hold_point(0.25) == pytest.approx(0.1) and w.room(0.1) == pytest.approx(0.2)
    one_sided = TravelWindow(xmin=-1.0)
    assert one_sided.finite and one_sided.hold_point(2.0) == 2.0 and one_sided.room(2.0) == 3.0
    assert not TravelWindow().finite


def test_the_plan_fits_the_window_and_says_when_nothing_can():
    base = make_design(1.0)
    plan = plan_closed_loop(SIM, base, 0.05, where="host", x_ref=0.0, cap=8.0)
    assert plan.predicted <= DESIGN_SHARE * 0.05
    assert min(plan.design.freqs_hz) >= 5 * plan.controller.gains.bandwidth_hz * (1 - 1e-9)
    assert plan.design.amplitude >= 1.0  # the window spent on a larger amplitude, not lost
    # the plan's prediction is what the hold does: simulated independently of the search
    again = simulate_hold(SIM, plan.controller, design_excitation(plan.design).u1[: 2 * 4000])
    assert again.excursion() == pytest.approx(plan.predicted)
    with pytest.raises(UsageError, match=r"window is too small .* widen the travel \(xmin/xmax\)"):
        plan_closed_loop(SIM, base, 1e-4, where="host", x_ref=0.0)
    given = base.with_amplitude(4.0)
    with pytest.raises(UsageError, match=r"lower --amplitude .* raise the lowest of --freqs"):
        plan_closed_loop(SIM, given.with_freqs((0.25, 0.5)), 0.01, where="host", x_ref=0.0,
                         amplitude_given=True, freqs_given=True)  # fmt: skip
