"""The SIDBE procedure on an axis with limited travel: excite in closed loop, inside the window.

1. Learn the axis: from what is known already (a bump test's model), else a
   relay probe (:mod:`servobench.bench.run.probe`, ``probe.csv``). A drive
   that takes a command only under its own hold (:attr:`~servobench.drivers.base.Drive.hold_only`),
   or one that holds with its own loop where no travel window is set, has no
   free torque for a relay: it learns the axis from a first trial under its
   hold instead (``hold-trial.csv``: one period of ``u1`` and of ``u2`` at the
   amplitude given, else the default, doubled while it yields no model), and
   the drive's gains are fitted to the same trial. Such a drive holds where the
   axis stands, and its window may be unbounded: the hold keeps the axis near
   its start, and step 6 then grows the amplitude up to its cap.
2. Plan (:mod:`servobench.bench.run.travel`): the hold loop's gains, the
   amplitude (unless given: from twice the larger Coulomb level, at least
   the relay level that swung, up to what the window allows) and the lowest
   excited line, so that the travel predicted by simulating the hold fits
   :data:`~servobench.bench.run.travel.DESIGN_SHARE` of the room around the
   held position (the middle of the window). A drive's own loop has gains
   the host does not know: a short trial under it (``hold-trial.csv``,
   half the amplitude, one period) measures them from the torque the drive
   reports applied, and the plan is made again with them.
3. Stream u1 and u2 under the hold (:mod:`servobench.bench.run.closed`): the
   drive's own loop where it has one (:attr:`~servobench.drivers.base.Drive.supports_drive_hold`),
   else the host's; the log carries ``u`` (total command), ``u_exc``,
   ``x_ref`` and ``loop = closed`` with the controller.
4. Identify the model as in open loop; the estimators use the excitation as
   instrument (:mod:`servobench.bench.identify`).
5. Step 6: while the verification fit is below the threshold, raise the
   amplitude by ``growth``, but only while the travel the last round
   measured, scaled by the growth the model predicts, stays within
   :data:`~servobench.bench.run.travel.GROWTH_SHARE` of the room.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from servobench.bench.identify.auto import identify
from servobench.bench.log.io import read_log
from servobench.bench.model.servo import IdentificationResult, ServoModel
from servobench.bench.procedure import excitation as exc
from servobench.bench.procedure.run_folder import HOLD_TRIAL_LOG, round_log_name
from servobench.bench.run.closed import stream_closed_runs
from servobench.bench.run.hold import (
    LINE_OVER_BANDWIDTH,
    HoldController,
    HoldGains,
    design_hold,
    fit_hold_gains,
)
from servobench.bench.run.probe import PROBE_LOG, probe_start, run_probe
from servobench.bench.run.runner import default_pace
from servobench.bench.run.travel import (
    AMPLITUDE_OVER_FRICTION,
    HOLD_AUTHORITY,
    ClosedLoopPlan,
    TravelWindow,
    growth_fits,
    plan_closed_loop,
    predict_travel,
)
from servobench.drivers.base import Drive
from servobench.errors import IdentificationError, UsageError

if TYPE_CHECKING:
    from servobench.bench.procedure.sidbe import Iteration, SidbeOptions

#: Doublings the probe may try without a drive limit (max_u) or --max-amplitude.
PROBE_DOUBLINGS = 10
#: Without max_u or --max-amplitude, the amplitude may grow to this multiple of the first.
UNLIMITED = 8.0
#: The trial under a drive's own hold: this share of the first round's u1, one period.
TRIAL_SCALE = 0.5
#: A trial that learns the axis under the drive's hold stands in for its unknown loop with the
#: host's design for this plant [command units s^2 / position unit, command units s / position
#: unit] (the log says the drive's own gains are not known; nothing else uses them).
NOMINAL_M, NOMINAL_B = 1.0, 1.0

#: The best round: its result, design, log and the cycle rate achieved streaming it [Hz].
Best = tuple[IdentificationResult, exc.ExcitationDesign, Path, float]


def closed_rounds(
    drive: Drive,
    options: SidbeOptions,
    out: Path,
    progress: Callable[[int, int, int], None] | None,
    known: ServoModel | None,
    record: Callable[..., Iteration],
) -> tuple[list[Iteration], Best | None, dict[str, Any]]:
    """The rounds of the procedure in closed loop (see module docstring).

    ``record`` builds the :class:`~servobench.bench.procedure.sidbe.Iteration` of a round.
    Returns the rounds, the best ``(result, design, log, fs_achieved_hz)``, and the facts of the hold
    (for ``model.json``).
    """
    pace = options.pace or drive.url.get_str("pace", "") or default_pace(drive)
    plan, learnt, cap = prepare(drive, options, out / PROBE_LOG, out / HOLD_TRIAL_LOG, pace, known)
    iterations: list[Iteration] = []
    best: Best | None = None
    for index in range(1, int(options.max_iterations) + 1):
        result, error, share, achieved_hz = _round(drive, options, plan, out, index, pace, progress)
        log_path = out / round_log_name(index)
        if result is not None and (best is None or result.fit_percent > best[0].fit_percent):
            best = (result, plan.design, log_path, achieved_hz)
        fit = None if result is None else result.fit_percent
        method = None if result is None else result.method
        d = plan.design
        this_round = partial(record, index, d.amplitude, d.freqs_hz, fit, method, log_path)
        if fit is not None and fit >= options.fit_threshold:
            iterations.append(this_round("accepted", error, share))
            break
        action, plan_next = _grow(plan, result, share, cap, options.growth)
        if plan_next is not None and index == options.max_iterations:
            action, plan_next = "stopped: iteration limit reached", None
        iterations.append(this_round(action, error, share))
        if plan_next is None:
            break
        plan = plan_next
    shares = [it.travel_share for it in iterations if it.travel_share is not None]
    return iterations, best, {**facts(plan), "travel_share": max(shares, default=0.0), **learnt}


def prepare(
    drive: Drive, options: SidbeOptions, probe_log: Path, trial_log: Path, pace: str,
    known: ServoModel | None = None,
) -> tuple[ClosedLoopPlan, dict[str, Any], float]:  # fmt: skip
    """Learn the axis (``known``, else a relay probe into ``probe_log``) and plan the first
    round; for a drive's own loop, fit its gains to a trial (``trial_log``) and plan again.

    Returns the plan, what was learnt (for ``model.json``), and the highest amplitude
    the rounds may reach.
    """
    window = TravelWindow.of(drive.limits)
    if not window.finite and not drive.supports_drive_hold:
        raise UsageError(
            "closed loop holds the axis inside its travel, and the drive sets none: "
            "give xmin/xmax in the drive URL, or run with --loop open"
        )
    base = options.design()
    learnt: dict[str, Any]
    if known is None and (drive.hold_only or not window.finite):
        return _prepare_under_hold(drive, options, base, window, trial_log, pace)
    if known is None:
        cap = options.max_amplitude or drive.limits.max_command
        start = probe_start(options.amplitude, drive.limits.max_command)
        if not math.isfinite(cap):
            cap = start * 2.0**PROBE_DOUBLINGS
        probe = run_probe(drive, window, base.fs_hz, start, cap, probe_log, pace=pace)
        model, x0, level = probe.model, probe.x_start, probe.amplitude
        learnt = {"probe": probe.as_dict()}
    else:
        model, x0, level = known, drive.read().position, 0.0
        learnt = {"known": known.as_dict()}
    if options.amplitude is None:
        friction = max(model.coulomb_pos, model.coulomb_neg)
        amplitude = max(AMPLITUDE_OVER_FRICTION * friction, level) or base.amplitude
        base = base.with_amplitude(min(amplitude, _cap(drive, options, amplitude)))
    cap = _cap(drive, options, base.amplitude)
    try:
        plan = _first_plan(drive, options, base, model, window, x0, cap)
    except UsageError as err:
        kept = f"; probe log kept in {probe_log}" if known is None else ""
        raise UsageError(f"{err}{kept}") from None
    if plan.controller.where == "drive":
        gains = _drive_gains(drive, options, plan, trial_log, pace)
        if gains is not None:
            plan = _first_plan(drive, options, base, model, window, x0, cap, gains)
        learnt["drive_loop"] = (
            f"gains fitted to {trial_log.name}" if gains else f"the drive reported no applied "
            f"torque in {trial_log.name}: its travel predicted with the host's design"
        )
    return plan, learnt, cap


def _cap(drive: Drive, options: SidbeOptions, start: float) -> float:
    """The highest amplitude in closed loop: ``--max-amplitude``, else ``max_u`` less the hold's
    share (:data:`~servobench.bench.run.travel.HOLD_AUTHORITY`), else :data:`UNLIMITED` x ``start``."""
    if options.max_amplitude is not None:
        return min(options.max_amplitude, drive.limits.max_command)
    limit = drive.limits.max_command
    return (1.0 - HOLD_AUTHORITY) * limit if math.isfinite(limit) else UNLIMITED * start


def _first_plan(
    drive: Drive, options: SidbeOptions, base: exc.ExcitationDesign, model: ServoModel,
    window: TravelWindow, x0: float, cap: float, gains: HoldGains | None = None,
) -> ClosedLoopPlan:  # fmt: skip
    """The first round's plan (see :func:`~servobench.bench.run.travel.plan_closed_loop`)."""
    limits = drive.limits
    x_ref = x0 if drive.hold_only else window.hold_point(x0)  # hold-only: no free torque to move it
    where = "drive" if drive.supports_drive_hold else "host"
    return plan_closed_loop(
        model, base, window.room(x_ref), where=where, x_ref=x_ref, max_u=limits.max_command,
        max_v=limits.max_velocity, cap=cap, amplitude_given=options.amplitude is not None,
        freqs_given=options.freqs_hz is not None, gains=gains,
    )  # fmt: skip


def _prepare_under_hold(
    drive: Drive, options: SidbeOptions, base: exc.ExcitationDesign, window: TravelWindow,
    trial_log: Path, pace: str,
) -> tuple[ClosedLoopPlan, dict[str, Any], float]:  # fmt: skip
    """:func:`prepare` where the axis is learnt from a trial under the drive's own hold (see
    the module docstring): the model and the drive's gains from ``trial_log``, then the plan."""
    x0 = drive.read().position
    start = options.amplitude if options.amplitude is not None else base.amplitude
    cap = _cap(drive, options, start)
    amplitude = min(start, cap)
    tries = 0 if options.amplitude is not None else PROBE_DOUBLINGS
    for attempt in range(tries + 1):
        try:
            model, gains = _hold_trial(drive, options, base.with_amplitude(amplitude), window, x0,
                                       trial_log, pace)  # fmt: skip
            break
        except IdentificationError as err:
            if attempt == tries or amplitude >= cap:
                raise IdentificationError(
                    f"the trial under the drive's own hold yielded no model at ±{amplitude:.4g} "
                    f"({err}); log kept in {trial_log}. Give a larger --amplitude (within max_u)"
                ) from None
            amplitude = min(2.0 * amplitude, cap)
    learnt: dict[str, Any] = {
        "trial": {"amplitude": amplitude, "log": trial_log.name, "model": model.as_dict()},
        "drive_loop": f"gains fitted to {trial_log.name}" if gains else (
            f"the drive reported no applied torque in {trial_log.name}: its travel predicted with "
            "the host's design"),
    }  # fmt: skip
    if options.amplitude is None:
        friction = max(model.coulomb_pos, model.coulomb_neg)
        chosen = max(AMPLITUDE_OVER_FRICTION * friction, amplitude)
        base = base.with_amplitude(min(chosen, _cap(drive, options, chosen)))
    cap = _cap(drive, options, base.amplitude)
    try:
        plan = _first_plan(drive, options, base, model, window, x0, cap, gains)
    except UsageError as err:
        raise UsageError(f"{err}; trial log kept in {trial_log}") from None
    return plan, learnt, cap


def _hold_trial(
    drive: Drive, options: SidbeOptions, design: exc.ExcitationDesign, window: TravelWindow,
    x0: float, log: Path, pace: str,
) -> tuple[ServoModel, HoldGains | None]:  # fmt: skip
    """One period of ``u1`` and of ``u2`` of ``design`` under the drive's hold at ``x0``, logged
    to ``log``: the model identified from it (closed loop: the excitation as instrument) and the
    drive's gains fitted to it (None when it reports no applied torque).

    Raises
    ------
    IdentificationError
        The trial yields no model (the axis did not break away, say).
    """
    n = design.samples_per_period
    e = exc.design_excitation(design)
    stand_in = ServoModel(NOMINAL_M, NOMINAL_B, 0.0, 0.0)
    low = max(min(design.freqs_hz), design.fs_hz / n)
    ctrl = HoldController(design_hold(NOMINAL_M, NOMINAL_B, low / LINE_OVER_BANDWIDTH), "drive", x0,
                          1.0 / design.fs_hz, drive.limits.max_command)  # fmt: skip
    plan = ClosedLoopPlan(design, ctrl, window.room(x0), math.nan, stand_in)
    meta = {"experiment": "trial under the drive's own hold: the axis and the drive's gains are "
                          f"learnt from it (one period of u1 and of u2 at ±{design.amplitude:g})"}  # fmt: skip
    run = stream_closed_runs(drive, [(1, e.u1[:n]), (2, e.u2[:n])], design.fs_hz, log, plan,
                             metadata=meta, pace=pace, settle_s=options.settle_s)  # fmt: skip
    trial = read_log(run.log_path)
    model = identify(trial, "joint").model
    r = trial.run(1)
    gains = None
    if r.u_exc is not None and r.x_ref is not None and r.v is not None and r.x is not None:
        gains = fit_hold_gains(r.u - r.u_exc, r.x_ref - r.x, r.v, 1.0 / design.fs_hz)
    return model, gains


def _drive_gains(
    drive: Drive, options: SidbeOptions, plan: ClosedLoopPlan, log: Path, pace: str
) -> HoldGains | None:
    """The gains of the drive's own loop, fitted to a trial under its hold: one period of the
    first round's ``u1`` at :data:`TRIAL_SCALE` (``hold-trial.csv``); None when the drive
    reports no applied torque."""
    d = plan.design
    u = TRIAL_SCALE * exc.design_excitation(d).u1[: d.samples_per_period]
    meta = {"experiment": "trial under the drive's own hold (its gains are fitted to it)"}
    run = stream_closed_runs(drive, [(1, u)], d.fs_hz, log, plan, metadata=meta,
                             pace=pace, settle_s=options.settle_s)  # fmt: skip
    r = read_log(run.log_path).run(1)
    if r.u_exc is None or r.x_ref is None or r.v is None or r.x is None:
        return None
    return fit_hold_gains(r.u - r.u_exc, r.x_ref - r.x, r.v, 1.0 / d.fs_hz)


def _round(
    drive: Drive, options: SidbeOptions, plan: ClosedLoopPlan, out: Path, index: int, pace: str,
    progress: Callable[[int, int, int], None] | None,
) -> tuple[IdentificationResult | None, str, float, float]:  # fmt: skip
    """Stream one round and identify it: the result (or None and the error), the share of room
    used, the cycle rate achieved [Hz]."""
    design = plan.design

    def tick(done: int, total: int) -> None:
        if progress is not None:
            progress(index, done, total)

    run = stream_closed_runs(
        drive, exc.design_excitation(design).runs(), design.fs_hz, out / round_log_name(index), plan,
        metadata={**design.metadata(), "iteration": index}, pace=pace,
        settle_s=options.settle_s, progress=tick,
    )  # fmt: skip
    try:
        result = identify(read_log(run.log_path), options.method, resonance=options.resonance)
    except IdentificationError as err:
        return None, str(err), run.share, run.fs_achieved_hz
    return result, "", run.share, run.fs_achieved_hz


def _grow(
    plan: ClosedLoopPlan, result: IdentificationResult | None, share: float, cap: float, growth: float
) -> tuple[str, ClosedLoopPlan | None]:
    """Step 6 in closed loop: the action, and the next round's plan (None: stop)."""
    amplitude = plan.design.amplitude
    if amplitude >= cap:
        return "stopped: threshold not reached within the drive limits", None
    bigger = plan.design.with_amplitude(min(amplitude * growth, cap))
    if not math.isfinite(plan.room):  # no window: the drive's hold alone bounds the travel
        action = f"fit below threshold: amplitude raised to {bigger.amplitude:g}"
        return action, replace(plan, design=bigger)
    model = result.model if result is not None else None
    ratio = bigger.amplitude / amplitude
    if model is not None:
        now = predict_travel(model, plan.design, plan.controller)
        ratio = predict_travel(model, bigger, plan.controller) / now if now > 0 else ratio
    if not growth_fits(share * plan.room, plan.room, ratio):
        return (
            f"stopped: fit below threshold, and a larger amplitude would not fit the travel "
            f"(this round used {share:.0%} of the room, x{ratio:.2g} predicted)"
        ), None
    return (
        f"fit below threshold: amplitude raised to {bigger.amplitude:g} (this round used "
        f"{share:.0%} of the room, x{ratio:.2g} predicted)"
    ), replace(plan, design=bigger)


def facts(plan: ClosedLoopPlan) -> dict[str, Any]:
    """Where the hold ran and with what (the host's gains; a drive's own loop keeps its own)."""
    c, g = plan.controller, plan.controller.gains
    return {"where": c.where, "x_ref": c.x_ref, "room": plan.room, "kp": g.kp, "ki": g.ki,
            "kd": g.kd, "bandwidth_hz": g.bandwidth_hz if math.isfinite(g.bandwidth_hz) else None}  # fmt: skip
