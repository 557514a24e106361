"""The servo plant with extra physical effects, integrated in sub-steps with exact stick handling.

The base physics is that of :mod:`sim_backend.plant`; the effects of
:mod:`sim_backend.effects` contribute :class:`~sim_backend.effects.spec.Terms`:

* command transforms (quantization, saturation, dead zone, offset) and a
  transport delay act on ``u`` before the integrator (whole samples by
  shifting, the fraction by splitting each interval at the delay boundary);
* direction-dependent viscous friction, a velocity-dependent friction excess
  (Stribeck) and position-dependent forces (cogging) act on the motor body;
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
from collections.abc import Callable

import numpy as np

from drivers.errors import UsageError
from sim_backend.effects.spec import Terms
from sim_backend.plant import PlantParams, PlantState

#: Sub-steps per interval for terms that are not exact under constant force.
DEFAULT_SUBSTEPS = 2
#: Upper bound on sub-steps per interval (keeps a stiff resonance affordable).
MAX_SUBSTEPS = 16

Excess = Callable[[float, int], float] | None


def _consts(h: float, M: float, Bp: float, Bn: float) -> tuple[float, ...]:
    """Exact-exponential constants of a body of mass ``M`` over a segment ``h`` [s]."""
    tp, tn = M / Bp, M / Bn
    ap, an = math.exp(-h / tp), math.exp(-h / tn)
    return (h, Bp, Bn, tp, tn, ap, an, tp * (1.0 - ap), tn * (1.0 - an))


def slider(k: tuple[float, ...], fr: tuple) -> Callable[[float, float, float], tuple[float, float]]:
    """``step(v, x, f)``: advance one body by one segment under a constant applied force ``f``.

    Parameters
    ----------
    k : tuple
        :func:`_consts` of the segment.
    fr : tuple
        ``(fc_pos, fc_neg, brk_pos, brk_neg, excess)``: Coulomb and breakaway magnitudes,
        and the velocity-dependent friction excess or ``None``.

    Returns
    -------
    step : callable
        ``(v [units/s], x [units], f [command units]) -> (v, x)`` at the segment end; ``f`` is
        the applied force except friction and the body's own viscous term.
    """
    h, Bp, Bn, tp, tn, ap, an, gp, gn = k
    fcp, fcn, bkp, bkn, exc = fr
    log, exp = math.log, math.exp

    def step(v: float, x: float, f: float) -> tuple[float, float]:
        if v > 0.0:
            F = fcp if exc is None else fcp + exc(v, 1)
            B, tau, a, g = Bp, tp, ap, gp
        elif v < 0.0:
            F = -fcn if exc is None else -fcn - exc(-v, -1)
            B, tau, a, g = Bn, tn, an, gn
        else:
            if -bkn <= f <= bkp:
                return 0.0, x
            if f > 0.0:
                F = fcp if exc is None else fcp + exc(0.0, 1)
                B, a, g = Bp, ap, gp
            else:
                F = -fcn if exc is None else -fcn - exc(0.0, -1)
                B, a, g = Bn, an, gn
            vinf = (f - F) / B
            return vinf * (1.0 - a), x + vinf * h - vinf * g
        vinf = (f - F) / B
        vn = vinf + (v - vinf) * a
        if vn != 0.0 and (vn > 0.0) == (v > 0.0):
            return vn, x + vinf * h + (v - vinf) * g
        # The velocity reaches zero at tc inside the segment.
        tc = tau * log((v - vinf) / -vinf)
        x += vinf * tc + (v - vinf) * tau * (1.0 - exp(-tc / tau))
        if -bkn <= f <= bkp:
            return 0.0, x
        rest = h - tc
        if f > 0.0:
            F2 = fcp if exc is None else fcp + exc(0.0, 1)
            B2, tau2 = Bp, tp
        else:
            F2 = -fcn if exc is None else -fcn - exc(0.0, -1)
            B2, tau2 = Bn, tn
        vinf2 = (f - F2) / B2
        e2 = exp(-rest / tau2)
        return vinf2 * (1.0 - e2), x + vinf2 * rest - vinf2 * tau2 * (1.0 - e2)

    return step


class _Propagator:
    """Exact zero-order-hold transition of ``dz/dt = A z + b w`` over any interval ``t``.

    Uses the eigen-decomposition of ``A`` (one per system) so an arbitrary
    interval costs a few small products; a defective ``A`` falls back to
    ``scipy.linalg.expm`` of the augmented matrix.
    """

    #: Largest condition number of the eigenvector matrix trusted.
    MAX_COND = 1e8

    def __init__(self, A: np.ndarray, b: np.ndarray) -> None:
        self.A, self.b = A, b
        lam, V = np.linalg.eig(A)
        self.ok = bool(np.isfinite(lam).all() and np.linalg.cond(V) < self.MAX_COND)
        if self.ok:
            self.lam, self.V = lam, V
            self.Vinv = np.linalg.inv(V)
            self.Vinv_b = self.Vinv @ b

    def over(self, t: float) -> tuple[tuple[tuple[float, ...], ...], tuple[float, ...]]:
        """``(E, g)`` as nested tuples: ``z(t) = E z(0) + g w``."""
        if not self.ok:
            from scipy.linalg import expm

            n = self.A.shape[0]
            aug = np.zeros((n + 1, n + 1))
            aug[:n, :n] = self.A * t
            aug[:n, n] = self.b * t
            M = expm(aug)
            E, g = M[:n, :n], M[:n, n]
        else:
            lt = self.lam * t
            e = np.exp(lt)
            small = np.abs(lt) < 1e-8
            phi = np.where(small, t * (1 + lt / 2), (e - 1) / np.where(small, 1.0, self.lam))
            E = ((self.V * e) @ self.Vinv).real
            g = (self.V @ (phi * self.Vinv_b)).real
        return tuple(map(tuple, E.tolist())), tuple(g.tolist())


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


class RichModel:
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
            params.fc_pos,
            params.fc_neg,
            max(params.breakaway_pos, terms.static_pos),
            max(params.breakaway_neg, terms.static_neg),
            terms.friction_excess,
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
            terms.friction_excess is None and self._pos_force is None and terms.coupling is None
        )
        self._dt: float | None = None
        self._mats: dict[tuple, tuple] = {}
        self._systems: dict[tuple, _Propagator] = {}
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

    def _prepare(self, dt_s: float) -> None:
        if not dt_s > 0:
            raise UsageError("sample interval must be > 0 s")
        p, c = self.params, self.terms.coupling
        delay = self.terms.delay_s / dt_s
        self._whole = int(math.floor(delay + 1e-9))
        frac = delay - self._whole
        pattern = _pattern(self.substeps(dt_s), frac if frac > 1e-9 else 0.0)
        r = c.load_ratio if c is not None else 0.0
        segs = []
        fr = self.friction
        for share, prev in pattern:
            h = share * dt_s
            rigid = slider(_consts(h, p.M, self.B_pos, self.B_neg), fr)
            if c is None:
                segs.append((prev, h, rigid, rigid, ()))
                continue
            motor = slider(
                _consts(h, (1 - r) * p.M, (1 - r) * self.B_pos, (1 - r) * self.B_neg), fr
            )
            load = _consts(h, r * p.M, r * self.B_pos, r * self.B_neg)
            segs.append((prev, h, rigid, motor, load))
        self._segs = segs
        self._dt = dt_s

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
        v, x = self._hidden[0], self._hidden[1]
        segs, pf = self._segs, self._pos_force
        vs: list[float] = []
        xs: list[float] = []
        if pf is None and len(segs) == 1:  # one exact segment per interval: the fast path
            step = segs[0][2]
            for uc in cur:
                vs.append(v)
                xs.append(x)
                v, x = step(v, x, uc)
            self._hidden = (v, x, v, x, 0)
            return vs, xs
        for uc, up in zip(cur, prev, strict=True):
            vs.append(v)
            xs.append(x)
            for use_prev, _, step, _, _ in segs:
                f = up if use_prev else uc
                if pf is not None:
                    f -= pf(x)
                v, x = step(v, x, f)
        self._hidden = (v, x, v, x, 0)
        return vs, xs

    def _spring_system(self, sm: int, sl: int, held: bool) -> _Propagator:
        """The spring-coupled bodies as ``dz/dt = A z + b w`` (cached per direction pair).

        State ``(vm, xm, vl, xl)`` with the force on the motor as input ``w``; ``held``:
        the motor is stuck and the load moves alone, state ``(vl, xl)``, input ``k xm``.
        """
        key = (sm, sl, held)
        hit = self._systems.get(key)
        if hit is not None:
            return hit
        c, p = self.terms.coupling, self.params
        r = c.load_ratio
        Mm, Ml = (1 - r) * p.M, r * p.M
        Bm = (1 - r) * (self.B_pos if sm >= 0 else self.B_neg)
        Bl = r * (self.B_pos if sl >= 0 else self.B_neg)
        k, d = c.stiffness, c.damping
        if held:
            A = np.array([[-(Bl + d) / Ml, -k / Ml], [1.0, 0.0]])
            b = np.array([1.0 / Ml, 0.0])
        else:
            A = np.array(
                [
                    [-(Bm + d) / Mm, -k / Mm, d / Mm, k / Mm],
                    [1.0, 0.0, 0.0, 0.0],
                    [d / Ml, k / Ml, -(Bl + d) / Ml, -k / Ml],
                    [0.0, 0.0, 1.0, 0.0],
                ]
            )
            b = np.array([1.0 / Mm, 0.0, 0.0, 0.0])
        out = self._systems[key] = _Propagator(A, b)
        return out

    def _spring_step(self, h: float, sm: int, sl: int, held: bool, cache: bool = True) -> tuple:
        """Exact ZOH matrices over ``h`` (cached per segment length unless ``cache`` is off)."""
        key = (h, sm, sl, held)
        hit = self._mats.get(key) if cache else None
        if hit is not None:
            return hit
        out = self._spring_system(sm, sl, held).over(h)
        if cache:
            self._mats[key] = out
        return out

    def _spring_reverse(self, s0: tuple, th: float, h: float, sm: int, f: float, g: float) -> tuple:
        """A segment in which the motor velocity crosses zero at ``th * h``.

        Exact up to the crossing; then the motor sticks (within breakaway) or
        continues the other way, exactly, for the rest of the segment.
        """
        fcp, fcn, bkp, bkn, exc = self.friction
        c = self.terms.coupling
        sl = 1 if s0[2] >= 0.0 else -1
        A, b = self._spring_step(th * h, sm, sl, False, cache=False)
        vm, xm, vl, xl = (
            sum(a * z for a, z in zip(row, s0, strict=True)) + bi * g
            for row, bi in zip(A, b, strict=True)
        )
        rest = (1.0 - th) * h
        net = f + c.stiffness * (xl - xm) + c.damping * vl
        if -bkn <= net <= bkp:
            (c00, c01), (c10, c11) = (A2 := self._spring_step(rest, 1, sl, True, cache=False))[0]
            d0, d1 = A2[1]
            w = c.stiffness * xm
            return 0.0, xm, c00 * vl + c01 * xl + d0 * w, c10 * vl + c11 * xl + d1 * w
        if net > 0.0:
            sm2, F = 1, (fcp if exc is None else fcp + exc(0.0, 1))
        else:
            sm2, F = -1, (-fcn if exc is None else -fcn - exc(0.0, -1))
        A, b = self._spring_step(rest, sm2, sl, False, cache=False)
        s1 = (0.0, xm, vl, xl)
        return tuple(
            sum(a * z for a, z in zip(row, s1, strict=True)) + bi * (f - F)
            for row, bi in zip(A, b, strict=True)
        )

    def _run_spring(self, cur: list[float], prev: list[float], c) -> tuple[list, list]:
        """Motor (friction, forces) -- spring/damper -- load; the sensor sits on the load.

        The linear part is propagated exactly per segment with the friction
        held; a motor velocity that changes sign inside a segment stops at the
        (interpolated) crossing, and a motor at rest within breakaway is held
        while the load moves alone.
        """
        vm, xm, vl, xl, _ = self._hidden
        fcp, fcn, bkp, bkn, exc = self.friction
        segs, pf = self._segs, self._pos_force
        kk, cc = c.stiffness, c.damping
        step = self._spring_step
        last = None
        vs: list[float] = []
        xs: list[float] = []
        for uc, up in zip(cur, prev, strict=True):
            vs.append(vl)
            xs.append(xl)
            for use_prev, h, _, _, _ in segs:
                f = up if use_prev else uc
                if pf is not None:
                    f -= pf(xm)
                sl = 1 if vl >= 0.0 else -1
                if vm > 0.0:
                    sm, F = 1, (fcp if exc is None else fcp + exc(vm, 1))
                elif vm < 0.0:
                    sm, F = -1, (-fcn if exc is None else -fcn - exc(-vm, -1))
                else:
                    net = f + kk * (xl - xm) + cc * vl
                    if -bkn <= net <= bkp:
                        (c00, c01), (c10, c11) = step(h, 1, sl, True)[0]
                        d0, d1 = step(h, 1, sl, True)[1]
                        w = kk * xm
                        vl, xl = c00 * vl + c01 * xl + d0 * w, c10 * vl + c11 * xl + d1 * w
                        continue
                    if net > 0.0:
                        sm, F = 1, (fcp if exc is None else fcp + exc(0.0, 1))
                    else:
                        sm, F = -1, (-fcn if exc is None else -fcn - exc(0.0, -1))
                key = (h, sm, sl)
                if key != last:
                    last = key
                    (
                        (
                            (a00, a01, a02, a03),
                            (a10, a11, a12, a13),
                            (a20, a21, a22, a23),
                            (a30, a31, a32, a33),
                        ),
                        (b0, b1, b2, b3),
                    ) = step(h, sm, sl, False)
                g = f - F
                n0 = a00 * vm + a01 * xm + a02 * vl + a03 * xl + b0 * g
                n1 = a10 * vm + a11 * xm + a12 * vl + a13 * xl + b1 * g
                n2 = a20 * vm + a21 * xm + a22 * vl + a23 * xl + b2 * g
                n3 = a30 * vm + a31 * xm + a32 * vl + a33 * xl + b3 * g
                if vm != 0.0 and (n0 > 0.0) != (vm > 0.0):
                    th = vm / (vm - n0)
                    vm, xm, vl, xl = self._spring_reverse((vm, xm, vl, xl), th, h, sm, f, g)
                else:
                    vm, xm, vl, xl = n0, n1, n2, n3
        self._hidden = (vm, xm, vl, xl, 0)
        return vs, xs

    def _run_gap(self, cur: list[float], prev: list[float], c) -> tuple[list, list]:
        """Motor (friction, forces) with a play of width ``gap`` to the load; sensor on the motor.

        Engaged, both move as one body and the contact force on the load is
        ``r (f - F_friction)``; the play opens when that force would pull.
        Closing it is an inelastic impact that conserves momentum.
        """
        vm, xm, vl, xl, side = self._hidden
        fr, segs, pf = self.friction, self._segs, self._pos_force
        fcp, fcn, bkp, bkn, exc = fr
        r = c.load_ratio
        half = 0.5 * c.gap
        vs: list[float] = []
        xs: list[float] = []
        for uc, up in zip(cur, prev, strict=True):
            vs.append(vm)
            xs.append(xm)
            for use_prev, h, rigid, motor, kl in segs:
                f = up if use_prev else uc
                if pf is not None:
                    f -= pf(xm)
                if side:
                    # Friction the joint body would feel; the contact force is r (f - F).
                    if vm > 0.0:
                        F = fcp if exc is None else fcp + exc(vm, 1)
                    elif vm < 0.0:
                        F = -fcn if exc is None else -fcn - exc(-vm, -1)
                    elif -bkn <= f <= bkp:
                        F = f
                    else:
                        F = fcp if f > 0 else -fcn
                    if side * (f - F) < 0.0:
                        side = 0
                if side:
                    vm, xm = rigid(vm, xm, f)
                    vl, xl = vm, xm - side * half
                    continue
                v0, x0, w0, y0 = vm, xm, vl, xl
                vm, xm = motor(vm, xm, f)
                _, _, _, _, _, ap, an, gp, gn = kl
                a, g = (ap, gp) if vl >= 0.0 else (an, gn)
                xl += vl * g
                vl *= a
                d = xm - xl
                if d >= half and vm >= vl:
                    side = 1
                elif d <= -half and vm <= vl:
                    side = -1
                if side:
                    # Impact at the (interpolated) instant the play closes, then engaged.
                    d0 = x0 - y0
                    th = (side * half - d0) / (d - d0) if d != d0 else 1.0
                    th = min(max(th, 0.0), 1.0)
                    vi = (1.0 - r) * (v0 + th * (vm - v0)) + r * (w0 + th * (vl - w0))
                    xi = x0 + th * (xm - x0)
                    rest = (1.0 - th) * h
                    if rest > 1e-12 * h:
                        k_rest = _consts(rest, self.params.M, self.B_pos, self.B_neg)
                        vm, xm = slider(k_rest, fr)(vi, xi, f)
                    else:
                        vm, xm = vi, xi
                    vl, xl = vm, xm - side * half
        self._hidden = (vm, xm, vl, xl, side)
        return vs, xs
