"""The travel window and the closed-loop excitation that fits it.

An axis whose travel ``[xmin, xmax]`` is finite (one side or both) is excited
in closed loop (:mod:`servobench.bench.run.hold`). The hold keeps the axis
within :data:`MARGIN` of the room it has on either side of the held position
(a guard stops the run beyond it); the excitation is designed so that the
travel it is predicted to drive, by simulating the hold on the model known so
far, uses at most :data:`DESIGN_SHARE` of that room. The prediction raises the
lowest excited line, with it the hold's bandwidth (a fifth of that line), until
the predicted travel fits; when no lowest line up to a quarter of the top line
fits, it lowers the amplitude, down to what still breaks friction clearly
(:data:`MIN_AMPLITUDE_OVER_FRICTION`). Then it spends the window on
information: a somewhat higher lowest line with a larger amplitude moves the
axis as far but faster, further above friction (:func:`plan_closed_loop`).
SIDBE's step 6 raises the amplitude only while the travel measured, scaled by
the predicted growth, stays within :data:`GROWTH_SHARE`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.identify.output_error import Chunk, cramer_rao
from servobench.bench.model.servo import ServoModel
from servobench.bench.procedure import excitation as exc
from servobench.bench.run.hold import (
    LINE_OVER_BANDWIDTH,
    HoldController,
    HoldGains,
    HoldResponse,
    design_hold,
    simulate_hold,
)
from servobench.drivers.base import Limits
from servobench.errors import UsageError

#: Share of the room on each side of the held position the hold keeps the axis within.
MARGIN = 0.8
#: Share of the room the first excitation is designed to use (the model is still rough).
DESIGN_SHARE = 0.6
#: Share of the room step 6 may grow the measured travel to.
GROWTH_SHARE = 0.7
#: Default amplitude over the larger Coulomb level.
AMPLITUDE_OVER_FRICTION = 2.0
#: Smallest amplitude over the larger Coulomb level that still identifies friction.
MIN_AMPLITUDE_OVER_FRICTION = 1.3
#: Amplitude factor per try when no lowest line fits.
AMPLITUDE_STEP = 0.8
#: Periods of the excitation simulated to predict the travel (the first is the transient).
PREDICT_PERIODS = 2
#: Lowest lines (multiples of the first that fits) tried with more amplitude.
STRETCHES = (1.0, 1.4, 2.0)
#: Bisection steps of the largest amplitude that fits.
AMPLITUDE_SEARCH = 4
#: Without a cap, the amplitude may grow to this multiple of the first that fits.
UNLIMITED_GROWTH = 8.0
#: Share of max_u the excitation leaves to the hold loop.
HOLD_AUTHORITY = 0.2
#: The predicted peak speed stays within this share of max_v.
SPEED_SHARE = 0.5


@dataclass(frozen=True)
class TravelWindow:
    """The allowed travel ``[xmin, xmax]`` [position units]; either side may be infinite."""

    xmin: float = -math.inf
    xmax: float = math.inf

    @classmethod
    def of(cls, limits: Limits) -> TravelWindow:
        return cls(limits.min_position, limits.max_position)

    @property
    def finite(self) -> bool:
        """True when either side limits the travel (the axis cannot turn freely)."""
        return math.isfinite(self.xmin) or math.isfinite(self.xmax)

    def hold_point(self, x: float) -> float:
        """Where to hold an axis now at ``x``: the middle of a window finite on both sides, else ``x``."""
        if math.isfinite(self.xmin) and math.isfinite(self.xmax):
            return 0.5 * (self.xmin + self.xmax)
        return x

    def room(self, x: float) -> float:
        """Distance [position units] from ``x`` to the nearer limit (``inf`` without limits)."""
        return min(x - self.xmin, self.xmax - x)

    def describe(self) -> str:
        return f"[{self.xmin:.4g}, {self.xmax:.4g}]"


@dataclass(frozen=True)
class ClosedLoopPlan:
    """The excitation and hold loop of one closed-loop round.

    Attributes
    ----------
    design : ExcitationDesign
    controller : HoldController
        The host's hold loop (its gains also predict a drive-side hold).
    room : float
        Room on the nearer side of the held position [position units].
    predicted : float
        Predicted largest ``|x - x_ref|`` of the ``u1`` run [position units].
    model : ServoModel
        The model the plan was made with (it also feeds the move to ``x_ref`` forward).
    """

    design: exc.ExcitationDesign
    controller: HoldController
    room: float
    predicted: float
    model: ServoModel

    @property
    def predicted_share(self) -> float:
        return self.predicted / self.room if self.room > 0 else math.inf

    def host_controller(self) -> HoldController:
        """The host's loop of this plan: its controller, or for a drive's own loop the host's
        design for the same lowest line (it moves the axis before the drive holds it)."""
        c = self.controller
        if c.where == "host":
            return c
        low = max(min(self.design.freqs_hz), self.design.fs_hz / self.design.samples_per_period)
        gains = design_hold(self.model.M, self.model.B, low / LINE_OVER_BANDWIDTH)
        return HoldController(gains, "host", c.x_ref, c.dt_s, c.max_u)

    def metadata(self) -> dict[str, object]:
        """Log header lines: the controller's and the window's."""
        return {
            **self.controller.metadata(),
            "travel_room": self.room,
            "travel_predicted": self.predicted,
        }


def predict_travel(model: ServoModel, design: exc.ExcitationDesign, controller: HoldController) -> float:
    """Largest ``|x - x_ref|`` [position units] the ``u1`` run of ``design`` drives under the hold."""
    return _Trial.of(model, design, controller).predicted


@dataclass(frozen=True)
class _Trial:
    """One candidate: its design and loop, the travel and peak speed it is predicted to drive,
    and the simulated ``u1`` run (total command and velocity) that scores it."""

    design: exc.ExcitationDesign
    controller: HoldController
    predicted: float
    speed: float
    response: HoldResponse

    @classmethod
    def of(cls, model: ServoModel, design: exc.ExcitationDesign, controller: HoldController) -> _Trial:
        n = design.samples_per_period * min(PREDICT_PERIODS, design.periods)
        r = simulate_hold(model, controller, exc.design_excitation(design).u1[:n])
        return cls(design, controller, r.excursion(controller.x_ref), float(np.max(np.abs(r.v))), r)

    def b_spread(self, model: ServoModel) -> float:
        """Relative Cramér-Rao bound of ``B`` (per unit velocity noise) for the simulated run:
        what limits the pole's accuracy; ``inf`` when the run cannot tell the parameters."""
        chunk = Chunk(self.response.u, self.response.v, self.controller.dt_s)
        try:
            return cramer_rao(model, [chunk], 1.0)["B"] / model.B
        except (np.linalg.LinAlgError, ValueError):
            return math.inf


def plan_closed_loop(
    model: ServoModel,
    base: exc.ExcitationDesign,
    room: float,
    *,
    where: str,
    x_ref: float,
    max_u: float = math.inf,
    max_v: float = math.inf,
    cap: float = math.inf,
    amplitude_given: bool = False,
    freqs_given: bool = False,
    share: float = DESIGN_SHARE,
    gains: HoldGains | None = None,
) -> ClosedLoopPlan:
    """The excitation (from ``base``) and hold gains whose predicted travel fits ``share * room``.

    ``where`` the loop runs (``"host"``, ``"drive"``), ``x_ref`` the position
    it holds, ``max_u`` its limit. The host's gains are designed here, a fifth
    of the lowest line; a drive's own loop has its own, ``gains`` when they are
    known (:func:`~servobench.bench.run.hold.fit_hold_gains`), else the host's
    design stands in for them in the prediction.

    1. The lowest line is the lowest of :func:`~servobench.bench.procedure.excitation.lowest_line_choices`
       that fits at ``base.amplitude``, found by bisection; while none fits, the
       amplitude is lowered by :data:`AMPLITUDE_STEP`, down to
       :data:`MIN_AMPLITUDE_OVER_FRICTION` times the larger Coulomb level.
    2. Unless the amplitude is given (or the room is unlimited), the window is then used for information: for
       lowest lines at :data:`STRETCHES` of that one, the largest amplitude
       up to ``cap`` (and :data:`HOLD_AUTHORITY` short of ``max_u``) that fits, and of
       those the one with the smallest Cramér-Rao bound of ``B`` on its simulated run.
       The predicted peak speed stays within :data:`SPEED_SHARE` of ``max_v``.

    Raises
    ------
    UsageError
        Nothing identifiable fits: the message says what to change.
    """
    if not room > 0:
        raise UsageError(f"the axis has no room to move (room {room:.4g}); move it inside xmin/xmax")
    budget, speed_limit = share * room, SPEED_SHARE * max_v
    friction = max(model.coulomb_pos, model.coulomb_neg)
    floor = MIN_AMPLITUDE_OVER_FRICTION * friction if friction > 0 else base.amplitude / 8
    f0 = base.fs_hz / base.samples_per_period
    lows = (min(base.freqs_hz),) if freqs_given else exc.lowest_line_choices(base.fs_hz, base.samples_per_period)

    cache: dict[tuple[float, float], _Trial] = {}

    def trial(low: float, amplitude: float) -> _Trial:
        if (low, amplitude) not in cache:
            freqs = base.freqs_hz if freqs_given else exc.freqs_from(low, base.fs_hz, base.samples_per_period)
            design = exc.ExcitationDesign(base.fs_hz, base.samples_per_period, base.periods, freqs,
                                          amplitude, base.ratio)  # fmt: skip
            loop = gains or design_hold(model.M, model.B, max(low, f0) / LINE_OVER_BANDWIDTH)
            ctrl = HoldController(loop, where, x_ref, 1.0 / base.fs_hz, max_u)
            cache[low, amplitude] = _Trial.of(model, design, ctrl)
        return cache[low, amplitude]

    def fits(t: _Trial) -> bool:
        return t.predicted <= budget and t.speed <= speed_limit

    amplitude = base.amplitude
    while (i := _lowest_fit(lambda low, a=amplitude: fits(trial(low, a)), lows)) is None:
        if amplitude_given or amplitude * AMPLITUDE_STEP < floor:
            raise UsageError(_too_small(model, base, room, share, amplitude_given, freqs_given, friction))
        amplitude *= AMPLITUDE_STEP
    best = trial(lows[i], amplitude)
    top = min(cap, (1.0 - HOLD_AUTHORITY) * max_u)
    top = top if math.isfinite(top) else UNLIMITED_GROWTH * amplitude
    if amplitude_given or amplitude < base.amplitude or not top > amplitude or math.isinf(room):
        return ClosedLoopPlan(best.design, best.controller, room, best.predicted, model)
    spread = best.b_spread(model)
    stretched = {min(lows, key=lambda f: abs(f - k * lows[i])) for k in STRETCHES}
    for low in sorted(f for f in stretched if f >= lows[i]):
        t = _largest(lambda a, low=low: trial(low, a), fits, amplitude, top)
        if t is not None and (t_spread := t.b_spread(model)) < spread:
            best, spread = t, t_spread
    return ClosedLoopPlan(best.design, best.controller, room, best.predicted, model)


def _lowest_fit(fits, lows: tuple[float, ...]) -> int | None:
    """Index of the lowest of ``lows`` that fits (bisection: the travel falls as the lines rise)."""
    if not fits(lows[-1]):
        return None
    lo, hi = -1, len(lows) - 1  # lows[hi] fits; lows[lo] does not (or lo = -1)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if fits(lows[mid]) else (mid, hi)
    return hi


def _largest(trial, fits, lo: float, hi: float) -> _Trial | None:
    """The trial of the largest amplitude in ``[lo, hi]`` that fits (bisection on a log scale)."""
    if fits(top := trial(hi)):
        return top
    if not fits(good := trial(lo)):
        return None
    for _ in range(AMPLITUDE_SEARCH):
        mid = math.sqrt(lo * hi)
        if fits(t := trial(mid)):
            lo, good = mid, t
        else:
            hi = mid
    return good


def _too_small(model, base, room, share, amplitude_given, freqs_given, friction) -> str:
    """Why nothing fits, and what to change."""
    what = []
    if amplitude_given:
        what.append("lower --amplitude ([sidbe] amplitude)")
    if freqs_given:
        what.append("raise the lowest of --freqs ([sidbe] freqs_hz)")
    what.append("widen the travel (xmin/xmax)")
    if friction > 0 and not amplitude_given:
        why = (
            f"even at ±{MIN_AMPLITUDE_OVER_FRICTION:g} x the friction level {friction:.4g} "
            "with the highest lowest line"
        )
    else:
        why = f"at ±{base.amplitude:.4g}"
    return (
        f"the travel window is too small for an identifiable excitation: {why} the hold loop is "
        f"predicted to need more than {share:.0%} of the room of {room:.4g} around the held "
        f"position (model M = {model.M:.4g}, B = {model.B:.4g}); " + ", or ".join(what)
    )


def growth_fits(measured: float, room: float, ratio: float) -> bool:
    """Whether a round that travelled ``measured`` may grow its travel by ``ratio`` (step 6)."""
    return measured * ratio <= GROWTH_SHARE * room
