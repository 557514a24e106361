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

The loops below are the reference. A model whose terms are all data (every library effect
but the spring of a resonance) runs them compiled (:mod:`.kernels`, through :mod:`.compiled`),
with the same numbers; ``tests/test_compiled_plant.py`` holds the two together.

Sampling: ``v[k]``, ``x[k]`` at ``t_k``, before ``u[k]`` acts on ``[t_k, t_k + dt)``.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.bodies import Propagator, consts, slider
from servobench.sim_backend.physics.compiled import Packed, coupling_kind, pack, run
from servobench.sim_backend.physics.coulomb import PlantParams, PlantState
from servobench.sim_backend.physics.coupling import CouplingMixin
from servobench.sim_backend.physics.effects import collect_terms
from servobench.sim_backend.physics.effects.spec import Terms
from servobench.sim_backend.physics.kernels import PAIRS, SEG_COLS, carry_state

#: Sub-steps per interval for terms that are not exact under constant force.
DEFAULT_SUBSTEPS = 2
#: Upper bound on sub-steps per interval (keeps a stiff resonance affordable).
MAX_SUBSTEPS = 16
#: Steps whose segments are kept prepared (a plant integrated over irregular spans sees many).
PREPARED_STEPS = 64
#: The spring columns of a segment's row when there is no spring (see :meth:`RichModel.rows`).
_SPRING_PAD = (0.0,) * (SEG_COLS - PAIRS)
#: Shortest call integrated compiled [samples]: a call costs the compiled loop about 20 us
#: before its first sample, the reference loops about 0.5 us per sample (the simulated drive
#: steps one sample at a time). Both give the same numbers and keep the same state.
COMPILED_FROM = 32


#: Segment rows by everything they depend on (step, mass, viscous coefficients, segment pattern,
#: coupling): models that differ only in terms the rows do not hold (friction levels, forces,
#: command transforms; most of a Jacobian's columns) share them. The oldest go first.
_ROWS: dict[tuple, np.ndarray] = {}
ROWS_KEPT = 512


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
    reference : bool
        Integrate with the Python loops below even when the terms are data (the compiled
        integrator, :mod:`.kernels`, runs by default; the reference is what it is tested
        against).
    """

    def __init__(self, params: PlantParams, terms: Terms, reference: bool = False) -> None:
        self.params = params
        self.terms = terms
        self.reference = reference
        self.compiled_from = COMPILED_FROM
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
        self._prepared: dict[float, tuple] = {}  # step [s] -> (whole delay steps, segments, ...)
        self._packed: dict[float, Packed | None] = {}  # step [s] -> what the compiled loop reads
        self._mats: dict[tuple, tuple] = {}
        self._systems: dict[tuple, Propagator] = {}
        self.reset()

    # ------------------------------------------------------------ set-up
    def reset(self) -> None:
        """Forget the command history and the hidden states (second body, delay line)."""
        self._history = np.zeros(0)
        self._last: PlantState | None = None
        self._hidden = (0.0, 0.0, 0.0, 0.0, 0)  # motor v, x, load v, x, engaged side

    def carry_on(self, state: PlantState) -> None:
        """Restart the measured body at ``state``, carrying on the second body from where the last
        :meth:`simulate` left it (its offset and relative velocity, the engaged side of a play):
        :func:`.kernels.carry_state`, what no sensor sees kept across a restart."""
        start = np.array([state.v, state.x, state.v, state.x, 0.0])
        carry_state(np.array(self._hidden, dtype=float), start, coupling_kind(self.terms.coupling))
        vm, xm, vl, xl, side = start.tolist()
        self._hidden = (vm, xm, vl, xl, int(side))
        self._last = PlantState(state.v, state.x)  # :meth:`_sync` keeps what was carried

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
        self._packed.clear()

    def _prepare(self, dt_s: float) -> None:
        if not dt_s > 0:
            raise UsageError("sample interval must be > 0 s")
        hit = self._prepared.get(dt_s)
        if hit is not None:
            self._whole, self._pattern, self._rows, self._segs, self._inline = hit
            self._dt = dt_s
            return
        if len(self._prepared) >= PREPARED_STEPS:  # irregular steps (clock=real): keep it bounded
            self._prepared.clear()
            self._packed.clear()
            self._mats.clear()
        p, c = self.params, self.terms.coupling
        delay = self.terms.delay_s / dt_s
        self._whole = int(math.floor(delay + 1e-9))
        frac = delay - self._whole
        self._pattern = tuple(_pattern(self.substeps(dt_s), frac if frac > 1e-9 else 0.0))
        key = (dt_s, p.M, self.B_pos, self.B_neg, self._pattern, c)
        rows = _ROWS.get(key)
        if rows is None:
            rows = self._compute_rows(dt_s)
            if len(_ROWS) >= ROWS_KEPT:
                _ROWS.pop(next(iter(_ROWS)))
            _ROWS[key] = rows
        self._rows = rows
        self._segs = self._inline = None  # the reference loops' steppers: built when they run
        self._dt = dt_s
        self._prepared[dt_s] = (self._whole, self._pattern, rows, None, None)

    def _segment_consts(self, dt_s: float) -> list[tuple]:
        """Per segment of :attr:`_pattern`: ``(use_prev, h, whole body, motor alone, load
        alone)``, each body's :func:`consts` (without a coupling the motor is the whole body and
        there is no load)."""
        p, c = self.params, self.terms.coupling
        r = c.load_ratio if c is not None else 0.0
        out = []
        for share, prev in self._pattern:
            h = share * dt_s
            k_rigid = consts(h, p.M, self.B_pos, self.B_neg)
            if c is None:
                out.append((prev, h, k_rigid, k_rigid, None))
                continue
            k_motor = consts(h, (1 - r) * p.M, (1 - r) * self.B_pos, (1 - r) * self.B_neg)
            load = consts(h, r * p.M, r * self.B_pos, r * self.B_neg)
            out.append((prev, h, k_rigid, k_motor, load))
        return out

    def _compute_rows(self, dt_s: float) -> np.ndarray:
        """Per segment of :attr:`_pattern`, the numbers the compiled loop reads (see :meth:`rows`)."""
        rows = []
        for prev, h, k_rigid, k_motor, load in self._segment_consts(dt_s):
            if load is None:
                rows.append((float(prev), *k_rigid, *k_rigid, *k_rigid, *_SPRING_PAD))
            else:
                rows.append((float(prev), *k_rigid, *k_motor, *load, *self._spring_row(h)))
        out = np.array(rows, dtype=float).reshape(len(rows), -1)
        out.flags.writeable = False  # shared between models (:data:`_ROWS`)
        return out

    def _build_steppers(self) -> None:
        """The reference loops' segments at the prepared step: per segment ``(use_prev, h,
        whole-body stepper, motor stepper, load consts)`` and the inline coefficients of the
        whole body and of the motor alone (the steppers' own numbers)."""
        segs = []
        inline = []
        fr = self.friction
        for prev, h, k_rigid, k_motor, load in self._segment_consts(self._dt):
            rigid = slider(k_rigid, fr)
            if load is None:
                segs.append((prev, h, rigid, rigid, ()))
                inline.append((_coefficients(k_rigid), _coefficients(k_rigid)))
                continue
            segs.append((prev, h, rigid, slider(k_motor, fr), load))
            inline.append((_coefficients(k_rigid), _coefficients(k_motor)))
        self._segs, self._inline = segs, inline
        self._prepared[self._dt] = (self._whole, self._pattern, self._rows, segs, inline)

    def _spring_row(self, h: float) -> tuple[float, ...]:
        """A spring's transitions over a segment ``h`` [s] as the compiled loop reads them (the
        very matrices the reference loop uses); zeros without a spring."""
        c = self.terms.coupling
        if c is None or c.kind != "spring":
            return _SPRING_PAD
        out: list[float] = []
        for sm, sl in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            A, b = self._spring_step(h, sm, sl, False)
            out.extend(a for row in A for a in row)
            out.extend(b)
        for sl in (1, -1):
            A, b = self._spring_step(h, 1, sl, True)
            out.extend(a for row in A for a in row)
            out.extend(b)
        return tuple(out)

    def rows(self, dt_s: float) -> np.ndarray:
        """Per segment of an interval of ``dt_s`` [s], the numbers the compiled loop reads:
        uses the previous command, then the :func:`consts` of the whole body, of the motor
        alone and of the load alone (shape ``(segments, kernels.SEG_COLS)``)."""
        if dt_s != self._dt:
            self._prepare(dt_s)
        return self._rows

    def whole_delay(self, dt_s: float) -> int:
        """The transport delay's whole samples at a step of ``dt_s`` [s]."""
        if dt_s != self._dt:
            self._prepare(dt_s)
        return self._whole

    def packed(self, dt_s: float) -> Packed | None:
        """The model as the compiled loop reads it (``None``: a term is not data, or
        :attr:`reference`)."""
        if self.reference:
            return None
        if dt_s not in self._packed:
            self._packed[dt_s] = pack(self, dt_s)
        return self._packed[dt_s]

    def _line(self, u: np.ndarray, pk: Packed) -> np.ndarray:
        """The delay line and ``u``, transformed: ``prev[j] = line[j]``, ``cur[j] = line[j + 1]``
        of :meth:`_commands`."""
        need = self._whole + 1
        hist = self._history
        if hist.size < need:
            hist = np.concatenate([np.zeros(need - hist.size), hist])
        line = np.concatenate([hist[-need:], u])
        self._history = line[-need:]
        return pk.transform(line)

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
        c = self.terms.coupling
        pk = self.packed(dt_s) if u.size >= self.compiled_from else None
        if pk is not None:
            start = np.array([self._hidden], dtype=float)
            out_v, out_x, final = run([pk], [[self._line(u, pk)]], [(0, 0, u.size, 0)], start)
            vm, xm, vl, xl, side = final[0, 0].tolist()
            self._hidden = (vm, xm, vl, xl, int(side))
            measured_load = c is not None and c.measured == "load"
            out = PlantState(vl, xl) if measured_load else PlantState(vm, xm)
            self._last = out
            return out_v[0], out_x[0], PlantState(out.v, out.x)
        cur, prev = self._commands(u)
        if self._segs is None:
            self._build_steppers()
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
