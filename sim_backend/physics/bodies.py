"""Integration primitives of one body and of linear coupled bodies, exact under zero-order hold.

:func:`slider` advances one body with viscous, Coulomb (and optional
velocity-dependent) friction under a constant force over one segment, with
exact stick handling; :class:`Propagator` is the exact transition of a
linear system over any interval (spring-coupled bodies between friction
events).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np


def consts(h: float, M: float, Bp: float, Bn: float) -> tuple[float, ...]:
    """Exact-exponential constants of a body of mass ``M`` over a segment ``h`` [s]."""
    tp, tn = M / Bp, M / Bn
    ap, an = math.exp(-h / tp), math.exp(-h / tn)
    return (h, Bp, Bn, tp, tn, ap, an, tp * (1.0 - ap), tn * (1.0 - an))


def friction_force(v: float, f: float, fr: tuple, x: float = 0.0) -> float | None:
    """Friction on a body [command units, signed]: at velocity ``v``, or at rest under ``f``.

    ``None`` when the body rests and ``f`` is within breakaway (it stays at rest).
    ``fr`` as for :func:`slider`, which inlines the same rule on its hot path; ``x``
    [units] is the body's position, read only by a position-dependent friction term.
    """
    fcp, fcn, bkp, bkn, exc, at_x = fr
    if at_x is not None:
        extra = at_x(x)
        fcp, fcn, bkp, bkn = fcp + extra, fcn + extra, bkp + extra, bkn + extra
    if v > 0.0 or (v == 0.0 and f > bkp):
        return fcp if exc is None else fcp + exc(v, 1)
    if v < 0.0 or (v == 0.0 and f < -bkn):
        return -fcn if exc is None else -fcn - exc(-v, -1)
    return None


def slider(k: tuple[float, ...], fr: tuple) -> Callable[[float, float, float], tuple[float, float]]:
    """``step(v, x, f)``: advance one body by one segment under a constant applied force ``f``.

    Parameters
    ----------
    k : tuple
        :func:`consts` of the segment.
    fr : tuple
        ``(coulomb_pos, coulomb_neg, breakaway_pos, breakaway_neg, excess, at_x)``: Coulomb
        and breakaway magnitudes, the velocity-dependent friction excess or ``None``, and
        the position-dependent friction ``at_x(x)`` [command units] added to all four
        levels at the segment's start position, or ``None``.

    Returns
    -------
    step : callable
        ``(v [units/s], x [units], f [command units]) -> (v, x)`` at the segment end; ``f`` is
        the applied force except friction and the body's own viscous term.
    """
    h, Bp, Bn, tp, tn, ap, an, gp, gn = k
    fcp0, fcn0, bkp0, bkn0, exc, at_x = fr
    log, exp = math.log, math.exp

    def step(
        v: float, x: float, f: float, fcp=fcp0, fcn=fcn0, bkp=bkp0, bkn=bkn0
    ) -> tuple[float, float]:
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

    if at_x is None:
        return step

    def step_at(v: float, x: float, f: float) -> tuple[float, float]:
        extra = at_x(x)
        return step(v, x, f, fcp0 + extra, fcn0 + extra, bkp0 + extra, bkn0 + extra)

    return step_at


class Propagator:
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
