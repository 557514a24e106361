"""The servo plant with extra physical effects, integrated in sub-steps with exact stick handling.

The base physics is that of :mod:`servobench.sim_backend.physics.coulomb`; the effects of
:mod:`servobench.sim_backend.physics.effects` contribute :class:`~servobench.sim_backend.physics.effects.spec.Terms`:

* command transforms (quantization, saturation, dead zone, offset) and a
  transport delay act on ``u`` before the integrator (whole samples by
  shifting, the fraction by splitting each interval at the delay boundary);
* direction-dependent viscous friction, a velocity-dependent friction excess
  (Stribeck), friction that varies along the travel (position friction) and
  position-dependent forces (cogging) act on the motor body;
* a coupling adds a second body: a spring-damper (resonance; the sensor sits
  on the load) or a play (backlash; the sensor sits on the motor).

Each segment holds its forces constant and integrates the viscous term
exactly (exponential), so piecewise-linear models are exact with one segment
per interval. A body whose velocity reaches zero inside a segment stops at
the crossing time and stays at rest unless the force exceeds its breakaway
level, in which case it continues the other way for the rest of the segment:
no switching-function smoothing, no chatter at zero velocity.

Sampling: ``v[k]``, ``x[k]`` at ``t_k``, before ``u[k]`` acts on ``[t_k, t_k + dt)``.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.bodies import Propagator, consts, slider
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState
from servobench.sim_backend.physics.coupling import CouplingMixin
from servobench.sim_backend.physics.effects import collect_terms
from servobench.sim_backend.physics.effects.spec import Terms

#: Sub-steps per interval for terms that are not exact under constant force.
DEFAULT_SUBSTEPS = 2
#: Upper bound on sub-steps per interval (keeps a stiff resonance affordable).
MAX_SUBSTEPS = 16
#: Steps whose segments are kept prepared (a plant integrated over irregular spans sees many).
PREPARED_STEPS = 64


def _coefficients(k: tuple[float, ...]) -> tuple[float, ...]:
    """``(a_pos, a_neg, g_pos, g_neg, B_pos, B_neg)`` of :func:`consts` ``k``: what the hot loops'
    inline steps read, the very numbers the segment's :func:`slider` was built from."""
    return (k[5], k[6], k[7], k[8], k[1], k[2])


def _pattern(substeps: int, frac: float) -> list[tuple[float, bool]]:
    """Segments of one interval as ``(fraction of dt, uses the previous command)``."""
    cuts = {j / substeps for j in range(substeps + 1)}
    if 0.0 < frac < 1.0:
        cuts.add(frac)
    pts = sorted(cuts)
    out = []
    for lo, hi in zip(pts[:-1], pts[1:], strict=True):
        if hi - lo > 1e-12:
            out.append((hi - lo, hi <= frac + 1e-12))
    return out


class RichModel(CouplingMixin):
    """Simulation model of a plant with effects; see the module docstring.

    Parameters
    ----------
    params : PlantParams
        Base plant.
    terms : Terms
        Collected effect terms.
    """

    def __init__(self, params: PlantParams, terms: Terms) -> None:
        self.params = params
        self.terms = terms
        B, dB = params.B, terms.dB
        self.B_pos, self.B_neg = B + dB, B - dB
        if not (self.B_pos > 0 and self.B_neg > 0):
            raise UsageError(f"viscous asymmetry |dB| = {abs(dB):g} must stay below B = {B:g}")
        self.friction = (
            params.coulomb_pos,
            params.coulomb_neg,
            max(params.breakaway_pos, terms.static_pos),
            max(params.breakaway_neg, terms.static_neg),
            terms.friction_excess,
            terms.friction_at,
        )
        inputs = [fn for _, fn in sorted(terms.inputs, key=lambda item: item[0])]
        self._inputs = inputs
        forces = list(terms.position_forces)
        if not forces:
            self._pos_force = None
        elif len(forces) == 1:
            self._pos_force = forces[0]
        else:
            self._pos_force = lambda x: sum(fn(x) for fn in forces)
        self.exact = (
            terms.friction_excess is None
            and terms.friction_at is None
            and self._pos_force is None
            and terms.coupling is None
        )
        self._dt: float | None = None
        self._prepared: dict[float, tuple[int, list]] = {}  # step [s] -> (whole delay steps, segments)
        self._mats: dict[tuple, tuple] = {}
        self._systems: dict[tuple, Propagator] = {}
        self.reset()

    # ------------------------------------------------------------ set-up
    def reset(self) -> None:
        """Forget the command history and the hidden states (second body, delay line)."""
        self._history = np.zeros(0)
        self._last: PlantState | None = None
        self._hidden = (0.0, 0.0, 0.0, 0.0, 0)  # motor v, x, load v, x, engaged side

    def prime(self, u_past: np.ndarray, dt_s: float) -> None:
        """Fill the delay line with the commands applied before the next :meth:`simulate`."""
        if dt_s != self._dt:
            self._prepare(dt_s)
        self._history = np.asarray(u_past, dtype=float)[-(self._whole + 1) :].copy()

    def substeps(self, dt_s: float) -> int:
        if self.exact:
            return 1
        need = math.ceil(dt_s / self.terms.substep_s) if math.isfinite(self.terms.substep_s) else 1
        return int(min(MAX_SUBSTEPS, max(DEFAULT_SUBSTEPS, need)))

    def forget_step(self) -> None:
        """Drop what was prepared for a step (the terms changed: prepare again)."""
        self._dt = None
        self._prepared.clear()

    def _prepare(self, dt_s: float) -> None:
        if not dt_s > 0:
            raise UsageError("sample interval must be > 0 s")
        hit = self._prepared.get(dt_s)
        if hit is not None:
            self._whole, self._segs, self._inline = hit
            self._dt = dt_s
            return
        if len(self._prepared) >= PREPARED_STEPS:  # irregular steps (clock=real): keep it bounded
            self._prepared.clear()
            self._mats.clear()
        p, c = self.params, self.terms.coupling
        delay = self.terms.delay_s / dt_s
        self._whole = int(math.floor(delay + 1e-9))
        frac = delay - self._whole
        pattern = _pattern(self.substeps(dt_s), frac if frac > 1e-9 else 0.0)
        r = c.load_ratio if c is not None else 0.0
        segs = []
        inline = []  # per segment: coefficients of the whole body and of the motor alone
        fr = self.friction
        for share, prev in pattern:
            h = share * dt_s
            k_rigid = consts(h, p.M, self.B_pos, self.B_neg)
            rigid = slider(k_rigid, fr)
            if c is None:
                segs.append((prev, h, rigid, rigid, ()))
                inline.append((_coefficients(k_rigid), _coefficients(k_rigid)))
                continue
            k_motor = consts(h, (1 - r) * p.M, (1 - r) * self.B_pos, (1 - r) * self.B_neg)
            motor = slider(k_motor, fr)
            load = consts(h, r * p.M, r * self.B_pos, r * self.B_neg)
            segs.append((prev, h, rigid, motor, load))
            inline.append((_coefficients(k_rigid), _coefficients(k_motor)))
        self._segs, self._inline = segs, inline
        self._dt = dt_s
        self._prepared[dt_s] = (self._whole, segs, inline)

    def _commands(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Effective command held in each interval and in the interval before it (delay line)."""
        m = self._whole
        need = m + 1
        hist = self._history
        if hist.size < need:
            hist = np.concatenate([np.zeros(need - hist.size), hist])
        line = np.concatenate([hist[-need:], u])
        self._history = line[-need:]
        cur = line[1 : 1 + u.size]
        prev = line[: u.size]
        for fn in self._inputs:
            cur, prev = fn(cur), fn(prev)
        return np.asarray(cur, dtype=float), np.asarray(prev, dtype=float)

    def _sync(self, state: PlantState) -> None:
        """Hidden states consistent with a given measured state (second body relaxed)."""
        if self._last is not None and state.v == self._last.v and state.x == self._last.x:
            return
        self._hidden = (state.v, state.x, state.v, state.x, 0)

    # ------------------------------------------------------------ simulate
    def simulate(
        self, u: np.ndarray, dt_s: float, state: PlantState
    ) -> tuple[np.ndarray, np.ndarray, PlantState]:
        """Measured-body ``(v, x)`` at each interval start and the final state; see the module doc."""
        if dt_s != self._dt:
            self._prepare(dt_s)
        u = np.asarray(u, dtype=float)
        self._sync(state)
        cur, prev = self._commands(u)
        c = self.terms.coupling
        if c is None:
            vs, xs = self._run_rigid(cur.tolist(), prev.tolist())
        elif c.kind == "spring":
            vs, xs = self._run_spring(cur.tolist(), prev.tolist(), c)
        else:
            vs, xs = self._run_gap(cur.tolist(), prev.tolist(), c)
        vm, xm, vl, xl, _ = self._hidden
        out = PlantState(vl, xl) if c is not None and c.measured == "load" else PlantState(vm, xm)
        self._last = out
        return np.array(vs), np.array(xs), PlantState(out.v, out.x)

    def _run_rigid(self, cur: list[float], prev: list[float]) -> tuple[list, list]:
        """One body with every friction and force term; see the module docstring.

        The hot path -- a body that keeps moving one way through a segment -- is
        :func:`slider`'s own arithmetic written inline (the diagnosis's refits run
        it tens of millions of times); a body at rest or reversing goes through
        the segment's stepper.
        """
        v, x = self._hidden[0], self._hidden[1]
        segs, pf = self._segs, self._pos_force
        fcp0, fcn0, _, _, exc, at_x = self.friction
        vs: list[float] = []
        xs: list[float] = []
        push_v, push_x = vs.append, xs.append
        # per segment: (use_prev, h, stepper, a_pos, a_neg, g_pos, g_neg, B_pos, B_neg)
        plan = [(*seg[:3], *joint) for seg, (joint, _) in zip(segs, self._inline, strict=True)]
        for uc, up in zip(cur, prev, strict=True):
            push_v(v)
            push_x(x)
            for use_prev, h, step, ap, an, gp, gn, Bp, Bn in plan:
                f = up if use_prev else uc
                if pf is not None:
                    f -= pf(x)
                if v > 0.0:
                    F = fcp0 if at_x is None else fcp0 + at_x(x)
                    if exc is not None:
                        F = F + exc(v, 1)
                    vinf = (f - F) / Bp
                    vn = vinf + (v - vinf) * ap
                    if vn > 0.0:
                        x, v = x + vinf * h + (v - vinf) * gp, vn
                        continue
                elif v < 0.0:
                    F = -(fcn0 if at_x is None else fcn0 + at_x(x))
                    if exc is not None:
                        F = F - exc(-v, -1)
                    vinf = (f - F) / Bn
                    vn = vinf + (v - vinf) * an
                    if vn < 0.0:
                        x, v = x + vinf * h + (v - vinf) * gn, vn
                        continue
                v, x = step(v, x, f)
        self._hidden = (v, x, v, x, 0)
        return vs, xs


def build_model(params: PlantParams) -> RichModel:
    """The simulation model of a plant with effects: their terms collected, then integrated."""
    return RichModel(params, collect_terms(params))
