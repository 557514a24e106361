"""The plant's integrators compiled with numba: the loops of the reference integrators, with
the effects' terms read as data.

:mod:`servobench.sim_backend.physics.rich_plant` (one body), :mod:`.coupling` (the play) and
:func:`servobench.sim_backend.physics.coulomb.simulate_coulomb` (the base plant) are the
and the spring (resonance) are the reference: each function here is one of their loops
written again, operation for operation, over arrays, so the compiled outputs equal theirs
(``tests/test_compiled_plant.py``); a spring's reversal inside a segment propagates its
system over the fraction of the segment from the modes its reference holds (a defective
system, which has none, calls the reference's own step back: :func:`_reverse`). The
effects' callables become numbers (:class:`~.effects.spec.GaussianExcess`,
:class:`~.effects.spec.TableFriction`, :class:`~.effects.spec.SineForce`); a model is

* ``fpar`` [float, :data:`NF`]: friction levels, the excess, the table's origin and scale,
  the play, the mass, the viscous coefficients and the spring, indexed by the names below;
* ``ipar`` [int, :data:`NI`]: the kind of integrator, which terms are on, and where the
  model's rows start and end in the shared ``segs``, ``table`` and ``forces`` arrays;
* ``segs`` [float, (segments, :data:`SEG_COLS`)]: per segment of an interval, whether it holds
  the previous command, then the :func:`~.bodies.consts` of the whole body, of the motor
  alone and of the load alone, then a spring's transitions;
* ``table`` [float]: a :class:`~.effects.spec.TableFriction`'s values; ``forces`` [float,
  (n, 3)]: each :class:`~.effects.spec.SineForce`'s amplitude, spatial frequency and phase.

:func:`run_batch` integrates many models over many windows in one call: the diagnosis's
candidates and a Jacobian's columns. Every array is float64 or int64 and C-contiguous, so
each kernel is compiled once (``cache=True``: once per machine, not per process).
"""

from __future__ import annotations

import math
import weakref

import numpy as np
from numba import njit, objmode

# ------------------------------------------------------------------ the layout of a model
#: ``fpar`` indices.
FCP, FCN, BKP, BKN, EXC_POS, EXC_NEG, EXC_INV, AT_X0, AT_SCALE, HALF, RATIO, MASS, B_POS, B_NEG, DT, STIFF, DAMP, EXC_CUT = range(18)  # fmt: skip
NF = 18
#: ``ipar`` indices.
KIND, HAS_EXC, HAS_AT, SEG0, SEG1, TAB0, TAB1, FOR0, FOR1, KEY, MODE = range(11)
NI = 11
#: Integrators (``ipar[KIND]``): one body with every term, the play, the base plant, the spring.
RIGID, GAP, COULOMB, SPRING = 0, 1, 2, 3
#: ``segs`` columns: 0 uses the previous command; the consts of the whole body, the motor,
#: the load start at these columns (each ``h, Bp, Bn, tp, tn, ap, an, gp, gn``); then, for a
#: spring, the transition over the segment of the four motor/load direction pairs (``A``
#: row by row, then ``b``: 20 numbers each, :func:`spring_system`'s order) and of the load
#: alone behind a held motor for the two load directions (6 numbers each).
JOINT, MOTOR, LOAD, PAIRS, HELD = 1, 10, 19, 28, 108
SEG_COLS = 120
#: ``modes`` columns: a spring's six systems (:func:`spring_system`'s order), each as the
#: eigen-decomposition its reference :class:`~.bodies.Propagator` holds -- ``lam`` (n), ``V``
#: (n x n, row by row), ``V^-1`` (n x n), ``V^-1 b`` (n), n = 4 (2 for the held motor) -- in
#: :data:`MODE_COLS` complex numbers from ``MODE_COLS * system``. ``ipar[MODE]`` is the model's
#: row, -1 where a system is defective (its reversals then run on the reference).
MODE_COLS = 40
#: Spring models by ``ipar[KEY]``: the reversals of those without modes run on the reference
#: (:func:`_reverse`); each :class:`~.compiled.Packed` of a spring holds its model, which keeps
#: it here.
REVERSALS: weakref.WeakValueDictionary = weakref.WeakValueDictionary()

#: No reference counting (``_nrt``): the loops allocate nothing, and counting the arrays
#: handed from function to function cost more than the arithmetic.
_JIT = {"cache": True, "nogil": True, "error_model": "numpy", "_nrt": False}


@njit(**_JIT)
def _excess(speed, direction, fpar):
    """The excess at ``speed``; 0 past ``fpar[EXC_CUT]`` in ``z**2`` (:func:`excess_cut`),
    where the Coulomb level it is added to does not change by it."""
    z = speed * fpar[EXC_INV]
    if z * z > fpar[EXC_CUT]:
        return 0.0
    return (fpar[EXC_POS] if direction > 0 else fpar[EXC_NEG]) * math.exp(-z * z)


def excess_cut(pos: float, neg: float, fcp: float, fcn: float) -> float:
    """The ``z**2`` past which an excess ``max(pos, neg) exp(-z**2)`` is below ``2**-54`` of
    the smaller Coulomb level: added to that level, it rounds to the level itself (less than
    half its last place), so the kernels skip its ``exp`` there and their sums stay the
    reference's bit for bit. ``inf`` (never skipped) where a level is not positive."""
    top, floor = max(abs(pos), abs(neg)), min(fcp, fcn)
    if floor <= 0.0 or not math.isfinite(floor):
        return math.inf
    if top == 0.0:
        return 0.0
    return max(0.0, math.log(top / floor) + 54.0 * math.log(2.0) + 1.0)  # 1: a margin


@njit(**_JIT)
def _table(x, fpar, ipar, table):
    t0 = ipar[TAB0]
    last = ipar[TAB1] - t0 - 1
    s = (x - fpar[AT_X0]) * fpar[AT_SCALE]
    if s <= 0.0:
        return table[t0]
    if s >= last:
        return table[t0 + last]
    i = int(s)
    w = s - i
    return table[t0 + i] + w * (table[t0 + i + 1] - table[t0 + i])


@njit(**_JIT)
def _force(x, ipar, forces):
    f0, f1 = ipar[FOR0], ipar[FOR1]
    if f1 - f0 == 1:
        return forces[f0, 0] * math.sin(forces[f0, 1] * x + forces[f0, 2])
    acc = 0.0
    for i in range(f0, f1):
        acc += forces[i, 0] * math.sin(forces[i, 1] * x + forces[i, 2])
    return acc


@njit(**_JIT)
def _slide(v, x, f, h, Bp, Bn, tp, tn, ap, an, gp, gn, fpar, ipar, table):
    """:func:`~.bodies.slider`'s ``step``: one body over one segment under a constant force."""
    fcp, fcn, bkp, bkn = fpar[FCP], fpar[FCN], fpar[BKP], fpar[BKN]
    if ipar[HAS_AT]:
        extra = _table(x, fpar, ipar, table)
        fcp, fcn, bkp, bkn = fcp + extra, fcn + extra, bkp + extra, bkn + extra
    exc = ipar[HAS_EXC] != 0
    if v > 0.0:
        F = fcp + _excess(v, 1, fpar) if exc else fcp
        B, tau, a, g = Bp, tp, ap, gp
    elif v < 0.0:
        F = -fcn - _excess(-v, -1, fpar) if exc else -fcn
        B, tau, a, g = Bn, tn, an, gn
    else:
        if -bkn <= f <= bkp:
            return 0.0, x
        if f > 0.0:
            F = fcp + _excess(0.0, 1, fpar) if exc else fcp
            B, a, g = Bp, ap, gp
        else:
            F = -fcn - _excess(0.0, -1, fpar) if exc else -fcn
            B, a, g = Bn, an, gn
        vinf = (f - F) / B
        return vinf * (1.0 - a), x + vinf * h - vinf * g
    vinf = (f - F) / B
    vn = vinf + (v - vinf) * a
    if vn != 0.0 and (vn > 0.0) == (v > 0.0):
        return vn, x + vinf * h + (v - vinf) * g
    tc = tau * math.log((v - vinf) / -vinf)
    x += vinf * tc + (v - vinf) * tau * (1.0 - math.exp(-tc / tau))
    if -bkn <= f <= bkp:
        return 0.0, x
    rest = h - tc
    if f > 0.0:
        F2 = fcp + _excess(0.0, 1, fpar) if exc else fcp
        B2, tau2 = Bp, tp
    else:
        F2 = -fcn - _excess(0.0, -1, fpar) if exc else -fcn
        B2, tau2 = Bn, tn
    vinf2 = (f - F2) / B2
    e2 = math.exp(-rest / tau2)
    return vinf2 * (1.0 - e2), x + vinf2 * rest - vinf2 * tau2 * (1.0 - e2)


@njit(**_JIT)
def _slide_seg(v, x, f, segs, s, c, fpar, ipar, table):
    """:func:`_slide` with the consts of segment ``s`` starting at column ``c``."""
    return _slide(
        v, x, f,
        segs[s, c], segs[s, c + 1], segs[s, c + 2], segs[s, c + 3], segs[s, c + 4],
        segs[s, c + 5], segs[s, c + 6], segs[s, c + 7], segs[s, c + 8],
        fpar, ipar, table,
    )  # fmt: skip


@njit(**_JIT)
def _friction_force(v, f, x, fpar, ipar, table):
    """:func:`~.bodies.friction_force`; ``(force, held)``: ``held`` where it returns ``None``."""
    fcp, fcn, bkp, bkn = fpar[FCP], fpar[FCN], fpar[BKP], fpar[BKN]
    if ipar[HAS_AT]:
        extra = _table(x, fpar, ipar, table)
        fcp, fcn, bkp, bkn = fcp + extra, fcn + extra, bkp + extra, bkn + extra
    exc = ipar[HAS_EXC] != 0
    if v > 0.0 or (v == 0.0 and f > bkp):
        return (fcp + _excess(v, 1, fpar) if exc else fcp), False
    if v < 0.0 or (v == 0.0 and f < -bkn):
        return (-fcn - _excess(-v, -1, fpar) if exc else -fcn), False
    return 0.0, True


@njit(**_JIT)
def _rigid(line, i0, n, state, out_v, out_x, o0, fpar, ipar, segs, table, forces):
    """:meth:`~.rich_plant.RichModel._run_rigid`: ``prev = line[i0 + j]``, ``cur = line[i0 + j + 1]``."""
    v, x = state[0], state[1]
    fcp0, fcn0 = fpar[FCP], fpar[FCN]
    has_f = ipar[FOR1] > ipar[FOR0]
    has_at = ipar[HAS_AT] != 0
    exc = ipar[HAS_EXC] != 0
    s0, s1 = ipar[SEG0], ipar[SEG1]
    for j in range(n):
        up, uc = line[i0 + j], line[i0 + j + 1]
        out_v[o0 + j] = v
        out_x[o0 + j] = x
        for s in range(s0, s1):
            f = up if segs[s, 0] != 0.0 else uc
            if has_f:
                f -= _force(x, ipar, forces)
            if v > 0.0:
                F = fcp0 + _table(x, fpar, ipar, table) if has_at else fcp0
                if exc:
                    F = F + _excess(v, 1, fpar)
                vinf = (f - F) / segs[s, JOINT + 1]
                vn = vinf + (v - vinf) * segs[s, JOINT + 5]
                if vn > 0.0:
                    x, v = x + vinf * segs[s, 1] + (v - vinf) * segs[s, JOINT + 7], vn
                    continue
            elif v < 0.0:
                F = -(fcn0 + _table(x, fpar, ipar, table) if has_at else fcn0)
                if exc:
                    F = F - _excess(-v, -1, fpar)
                vinf = (f - F) / segs[s, JOINT + 2]
                vn = vinf + (v - vinf) * segs[s, JOINT + 6]
                if vn < 0.0:
                    x, v = x + vinf * segs[s, 1] + (v - vinf) * segs[s, JOINT + 8], vn
                    continue
            v, x = _slide_seg(v, x, f, segs, s, JOINT, fpar, ipar, table)
    state[0], state[1], state[2], state[3], state[4] = v, x, v, x, 0.0


@njit(**_JIT)
def _gap(line, i0, n, state, out_v, out_x, o0, fpar, ipar, segs, table, forces):
    """:meth:`~.coupling.CouplingMixin._run_gap`, the play; the sensor sits on the motor."""
    vm, xm, vl, xl, side = state[0], state[1], state[2], state[3], int(state[4])
    fcp, fcn = fpar[FCP], fpar[FCN]
    nfcn = -fcn
    has_f = ipar[FOR1] > ipar[FOR0]
    plain = ipar[HAS_EXC] == 0 and ipar[HAS_AT] == 0 and not has_f
    r, half = fpar[RATIO], fpar[HALF]
    M, B_pos, B_neg = fpar[MASS], fpar[B_POS], fpar[B_NEG]
    s0, s1 = ipar[SEG0], ipar[SEG1]
    for j in range(n):
        up, uc = line[i0 + j], line[i0 + j + 1]
        out_v[o0 + j] = vm
        out_x[o0 + j] = xm
        for s in range(s0, s1):
            h = segs[s, 1]
            f = up if segs[s, 0] != 0.0 else uc
            if has_f:
                f -= _force(xm, ipar, forces)
            if side:
                if plain and vm != 0.0:
                    F = fcp if vm > 0.0 else nfcn
                    held = False
                else:
                    F, held = _friction_force(vm, f, xm, fpar, ipar, table)
                if not held and side * (f - F) < 0.0:
                    side = 0
            v0, x0, w0, y0 = vm, xm, vl, xl
            c = JOINT if side else MOTOR
            if plain and vm > 0.0:
                vinf = (f - fcp) / segs[s, c + 1]
                vn = vinf + (vm - vinf) * segs[s, c + 5]
                if vn > 0.0:
                    xm, vm = xm + vinf * h + (vm - vinf) * segs[s, c + 7], vn
                else:
                    vm, xm = _slide_seg(vm, xm, f, segs, s, c, fpar, ipar, table)
            elif plain and vm < 0.0:
                vinf = (f - nfcn) / segs[s, c + 2]
                vn = vinf + (vm - vinf) * segs[s, c + 6]
                if vn < 0.0:
                    xm, vm = xm + vinf * h + (vm - vinf) * segs[s, c + 8], vn
                else:
                    vm, xm = _slide_seg(vm, xm, f, segs, s, c, fpar, ipar, table)
            else:
                vm, xm = _slide_seg(vm, xm, f, segs, s, c, fpar, ipar, table)
            if side:
                vl, xl = vm, xm - side * half
                continue
            if vl >= 0.0:
                xl += vl * segs[s, LOAD + 7]
                vl *= segs[s, LOAD + 5]
            else:
                xl += vl * segs[s, LOAD + 8]
                vl *= segs[s, LOAD + 6]
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
                    tp, tn = M / B_pos, M / B_neg
                    ap, an = math.exp(-rest / tp), math.exp(-rest / tn)
                    vm, xm = _slide(
                        vi, xi, f, rest, B_pos, B_neg, tp, tn, ap, an,
                        tp * (1.0 - ap), tn * (1.0 - an), fpar, ipar, table,
                    )  # fmt: skip
                else:
                    vm, xm = vi, xi
                vl, xl = vm, xm - side * half
    state[0], state[1], state[2], state[3], state[4] = vm, xm, vl, xl, float(side)


@njit(**_JIT)
def spring_system(sm, sl, held):
    """Index of a spring system: the four direction pairs of motor and load, then the load
    alone behind a held motor (``sm`` unused) for each load direction."""
    if held:
        return 4 if sl > 0 else 5
    return (0 if sm > 0 else 2) + (0 if sl > 0 else 1)


@njit(**_JIT)
def _over(mode, system, t):
    """The exponentials of a spring system's modes over ``t``: ``exp(lam_q t)`` and
    ``phi_q = (exp(lam_q t) - 1) / lam_q``, as :meth:`~.bodies.Propagator.over` takes them,
    once for every row :func:`_propagated` applies (a held motor's system uses two)."""
    at = MODE_COLS * system
    n = 2 if system >= 4 else 4
    e0 = e1 = e2 = e3 = p0 = p1 = p2 = p3 = 0j
    for q in range(n):
        lam = mode[at + q]
        lt = lam * t
        e = np.exp(lt)
        phi = t * (1 + lt / 2) if abs(lt) < 1e-8 else (e - 1) / lam
        if q == 0:
            e0, p0 = e, phi
        elif q == 1:
            e1, p1 = e, phi
        elif q == 2:
            e2, p2 = e, phi
        else:
            e3, p3 = e, phi
    return (e0, e1, e2, e3), (p0, p1, p2, p3)


@njit(**_JIT)
def _propagated(mode, system, ex, i, z0, z1, z2, z3, w):
    """Row ``i`` of :meth:`~.bodies.Propagator.over` ``(E, g)`` of a spring system, its
    exponentials ``ex`` over the interval from :func:`_over`, applied to the state ``z`` and
    the input ``w``: ``sum_j E_ij z_j + g_i w`` in the reference's order (a held motor's
    system has two states, ``z0, z1``)."""
    n = 2 if system >= 4 else 4
    at = MODE_COLS * system
    vi, ib = at + n, at + n + 2 * n * n
    es, phis = ex
    total = 0.0
    for j in range(n):
        e_ij = 0j
        for q in range(n):
            e_ij += (mode[vi + i * n + q] * es[q]) * mode[vi + n * n + q * n + j]
        z = z0 if j == 0 else z1 if j == 1 else z2 if j == 2 else z3
        total += e_ij.real * z
    g_i = 0j
    for q in range(n):
        g_i += mode[vi + i * n + q] * (phis[q] * mode[ib + q])
    return total + g_i.real * w


@njit(**_JIT)
def _reverse_compiled(mode, vm, xm, vl, xl, th, h, sm, f, g, fpar, ipar, table):
    """:meth:`~.coupling.CouplingMixin._spring_reverse` on the modes of the model's systems."""
    kk, cc = fpar[STIFF], fpar[DAMP]
    sl = 1 if vl >= 0.0 else -1
    t = th * h
    c = spring_system(sm, sl, False)
    ex = _over(mode, c, t)
    # the motor's own velocity at the crossing is 0: rows 1-3 only
    n1 = _propagated(mode, c, ex, 1, vm, xm, vl, xl, g)
    n2 = _propagated(mode, c, ex, 2, vm, xm, vl, xl, g)
    n3 = _propagated(mode, c, ex, 3, vm, xm, vl, xl, g)
    rest = (1.0 - th) * h
    net = f + kk * (n3 - n1) + cc * n2
    F, held = _friction_force(0.0, net, n1, fpar, ipar, table)
    if held:
        c = spring_system(1, sl, True)
        ex = _over(mode, c, rest)
        w = kk * n1
        return (
            0.0,
            n1,
            _propagated(mode, c, ex, 0, n2, n3, 0.0, 0.0, w),
            _propagated(mode, c, ex, 1, n2, n3, 0.0, 0.0, w),
        )
    c = spring_system(1 if net > 0.0 else -1, sl, False)
    ex = _over(mode, c, rest)
    return (
        _propagated(mode, c, ex, 0, 0.0, n1, n2, n3, f - F),
        _propagated(mode, c, ex, 1, 0.0, n1, n2, n3, f - F),
        _propagated(mode, c, ex, 2, 0.0, n1, n2, n3, f - F),
        _propagated(mode, c, ex, 3, 0.0, n1, n2, n3, f - F),
    )


def _reverse(key, vm, xm, vl, xl, th, h, sm, f, g):
    """A spring's reversal (the motor velocity crosses zero at ``th * h``), by the reference
    model's own :meth:`~.coupling.CouplingMixin._spring_reverse`: its exact propagation over
    a fraction of a segment, with the reference's own numbers. Only models with a defective
    system (no modes) take it."""
    return REVERSALS[key]._spring_reverse((vm, xm, vl, xl), th, h, sm, f, g)


@njit(**{**_JIT, "nogil": False})  # takes the GIL back for the call
def _reverse_py(key, vm, xm, vl, xl, th, h, sm, f, g):
    with objmode(a="float64", b="float64", c="float64", d="float64"):
        a, b, c, d = _reverse(key, vm, xm, vl, xl, th, h, sm, f, g)
    return a, b, c, d


@njit(**_JIT)
def _spring(line, i0, n, state, out_v, out_x, o0, fpar, ipar, segs, table, forces, modes):
    """:meth:`~.coupling.CouplingMixin._run_spring`: motor -- spring/damper -- load; the
    sensor sits on the load."""
    vm, xm, vl, xl = state[0], state[1], state[2], state[3]
    kk, cc = fpar[STIFF], fpar[DAMP]
    has_f = ipar[FOR1] > ipar[FOR0]
    s0, s1 = ipar[SEG0], ipar[SEG1]
    for j in range(n):
        up, uc = line[i0 + j], line[i0 + j + 1]
        out_v[o0 + j] = vl
        out_x[o0 + j] = xl
        for s in range(s0, s1):
            f = up if segs[s, 0] != 0.0 else uc
            if has_f:
                f -= _force(xm, ipar, forces)
            sl = 1 if vl >= 0.0 else -1
            net = f + kk * (xl - xm) + cc * (vl - vm)
            F, held = _friction_force(vm, net, xm, fpar, ipar, table)
            if held:  # the motor is held: the load moves alone
                c = HELD + 6 * (spring_system(1, sl, True) - 4)
                w = kk * xm
                vl, xl = (
                    segs[s, c] * vl + segs[s, c + 1] * xl + segs[s, c + 4] * w,
                    segs[s, c + 2] * vl + segs[s, c + 3] * xl + segs[s, c + 5] * w,
                )
                continue
            sm = 1 if vm > 0.0 or (vm == 0.0 and net > 0.0) else -1
            c = PAIRS + 20 * spring_system(sm, sl, False)
            g = f - F
            n0 = (
                segs[s, c] * vm
                + segs[s, c + 1] * xm
                + segs[s, c + 2] * vl
                + segs[s, c + 3] * xl
                + segs[s, c + 16] * g
            )
            n1 = (
                segs[s, c + 4] * vm
                + segs[s, c + 5] * xm
                + segs[s, c + 6] * vl
                + segs[s, c + 7] * xl
                + segs[s, c + 17] * g
            )
            n2 = (
                segs[s, c + 8] * vm
                + segs[s, c + 9] * xm
                + segs[s, c + 10] * vl
                + segs[s, c + 11] * xl
                + segs[s, c + 18] * g
            )
            n3 = (
                segs[s, c + 12] * vm
                + segs[s, c + 13] * xm
                + segs[s, c + 14] * vl
                + segs[s, c + 15] * xl
                + segs[s, c + 19] * g
            )
            if vm != 0.0 and (n0 > 0.0) != (vm > 0.0):
                th = vm / (vm - n0)
                if ipar[MODE] >= 0:
                    vm, xm, vl, xl = _reverse_compiled(
                        modes[ipar[MODE]], vm, xm, vl, xl, th, segs[s, 1], sm, f, g, fpar, ipar, table
                    )
                else:
                    vm, xm, vl, xl = _reverse_py(ipar[KEY], vm, xm, vl, xl, th, segs[s, 1], sm, f, g)
            else:
                vm, xm, vl, xl = n0, n1, n2, n3
    state[0], state[1], state[2], state[3], state[4] = vm, xm, vl, xl, 0.0


@njit(**_JIT)
def _coulomb(line, i0, n, state, out_v, out_x, o0, fpar):
    """:func:`~.coulomb.simulate_coulomb`: ``u[j] = line[i0 + j + 1]``."""
    M, B, dt_s = fpar[MASS], fpar[B_POS], fpar[DT]
    fcp, fcn, bkp, bkn = fpar[FCP], fpar[FCN], fpar[BKP], fpar[BKN]
    tau = M / B
    a = math.exp(-dt_s / tau)
    g = tau * (1.0 - a)
    v, x = state[0], state[1]
    for j in range(n):
        uk = line[i0 + j + 1]
        out_v[o0 + j] = v
        out_x[o0 + j] = x
        if v > 0.0 or (v == 0.0 and uk > bkp):
            f, forward = fcp, True
        elif v < 0.0 or uk < -bkn:
            f, forward = -fcn, False
        else:
            continue  # stuck for the whole interval
        vinf = (uk - f) / B
        vn = vinf + (v - vinf) * a
        if (vn > 0.0) == forward and vn != 0.0:
            x += vinf * dt_s + (v - vinf) * g
            v = vn
            continue
        tc = tau * math.log((v - vinf) / -vinf)
        x += vinf * tc + (v - vinf) * tau * (1.0 - math.exp(-tc / tau))
        rest = dt_s - tc
        if -bkn <= uk <= bkp:
            v = 0.0
            continue
        f2 = fcp if uk > bkp else -fcn
        vinf2 = (uk - f2) / B
        e2 = math.exp(-rest / tau)
        x += vinf2 * rest - vinf2 * tau * (1.0 - e2)
        v = vinf2 * (1.0 - e2)
    state[0], state[1], state[2], state[3], state[4] = v, x, v, x, 0.0


@njit(**_JIT)
def variable_dt_velocity(u, dts, M, B, fcp, fcn, bkp, bkn, v0, out):
    """:func:`servobench.bench.identify.simulation.simulate_variable_dt_reference` into ``out``:
    ``u[k]`` over the interval ``dts[k]`` after sample ``k`` (``dts`` one shorter than ``u``)."""
    v = v0
    n = u.size
    for k in range(n):
        out[k] = v
        v = stick_slip_step(v, u[k], dts[k] if k < n - 1 else 0.0, M, B, fcp, fcn, bkp, bkn)


@njit(**_JIT)
def stick_slip_step(v, uk, dt, M, B, fcp, fcn, bkp, bkn):
    """The exact stick-slip velocity ``dt`` [s] after ``v`` under the constant command ``uk``:
    the piecewise exponential of the base plant (:func:`variable_dt_velocity`'s step; the pair
    placement's residuals, :mod:`servobench.bench.identify.pair_placement`)."""
    if v > 0.0:
        f = fcp
    elif v < 0.0:
        f = -fcn
    elif uk > bkp:
        f = fcp
    elif uk < -bkn:
        f = -fcn
    else:
        return v
    tau = M / B
    vinf = (uk - f) / B
    vn = vinf + (v - vinf) * math.exp(-dt / tau)
    forward = v > 0.0 or (v == 0.0 and uk > bkp)
    if (vn > 0.0) == forward and vn != 0.0:
        return vn
    tc = tau * math.log((v - vinf) / -vinf)
    if -bkn <= uk <= bkp:
        return 0.0
    f2 = fcp if uk > bkp else -fcn
    return (uk - f2) / B * (1.0 - math.exp(-(dt - tc) / tau))


@njit(cache=True)
def play_engaged(x, gap):
    """:func:`~.effects.backlash.engaged`: whether a load behind a play of ``gap`` is driven."""
    half = 0.5 * gap
    out = np.zeros(x.size, dtype=np.bool_)
    xl = x[0] if x.size else 0.0
    for i in range(x.size):
        xi = x[i]
        if xi - xl > half:
            xl = xi - half
            out[i] = True
        elif xl - xi > half:
            xl = xi + half
            out[i] = True
    return out


@njit(cache=True)
def carry_state(prev, state, kind):
    """A restart at the measured ``state`` that keeps what no sensor sees from ``prev`` (the state
    where the window before ended): the second body's offset and relative velocity, and the
    engaged side of a play. The measured body (a play's motor, a spring's load) takes ``state``;
    the other follows it by ``prev``'s differences. A rigid model has no second body."""
    if kind == GAP:
        state[2] = state[0] + (prev[2] - prev[0])
        state[3] = state[1] + (prev[3] - prev[1])
        state[4] = prev[4]
    elif kind == SPRING:
        state[0] = state[2] + (prev[0] - prev[2])
        state[1] = state[3] + (prev[1] - prev[3])
        state[4] = prev[4]


@njit(**_JIT)
def run_batch(fpar, ipar, segs, table, forces, modes, line, line_at, windows, start, carry, out_v, out_x,
              final):  # fmt: skip
    """Every model over every window, in one call.

    Parameters
    ----------
    fpar, ipar : ndarray, shapes (P, NF), (P, NI)
        The models (rows of ``segs``, ``table`` and ``forces`` by the offsets in ``ipar``).
    segs, table, forces : ndarray
        The rows of all models, concatenated.
    modes : ndarray of complex, shape (S, 6 * MODE_COLS)
        The springs' modes (a row per spring model, ``ipar[MODE]``).
    line : ndarray, shape (L,)
        Every model's command lines [command units], concatenated: the transformed command
        held in each interval, one interval before a window's first (see :func:`_rigid`).
    line_at : ndarray of int, shape (P, R)
        Where model ``p``'s line of run ``r`` starts in ``line``.
    windows : ndarray of int, shape (W, 4)
        Per window: run, first sample in its run's line, samples, first output column.
    start : ndarray, shape (W, 5)
        The state at each window's start: motor ``v, x``, load ``v, x``, engaged side.
    carry : ndarray of bool, shape (W,)
        Per window: it continues the window before it, whose second body it carries on
        (:func:`carry_state`; the measured body still starts at ``start``).
    out_v, out_x : ndarray, shape (P, N)
        Velocity [units/s] and position [units] of the measured body at each sample.
    final : ndarray, shape (P, W, 5)
        The state at each window's end.
    """
    for p in range(fpar.shape[0]):
        fp, ip = fpar[p], ipar[p]
        kind = ip[KIND]
        ov, ox = out_v[p], out_x[p]
        for w in range(windows.shape[0]):
            state = final[p, w]
            for i in range(5):
                state[i] = start[w, i]
            if carry[w] and w > 0:
                carry_state(final[p, w - 1], state, kind)
            i0 = line_at[p, windows[w, 0]] + windows[w, 1]
            n, o0 = windows[w, 2], windows[w, 3]
            if kind == COULOMB:
                _coulomb(line, i0, n, state, ov, ox, o0, fp)
            elif kind == RIGID:
                _rigid(line, i0, n, state, ov, ox, o0, fp, ip, segs, table, forces)
            elif kind == GAP:
                _gap(line, i0, n, state, ov, ox, o0, fp, ip, segs, table, forces)
            else:
                _spring(line, i0, n, state, ov, ox, o0, fp, ip, segs, table, forces, modes)
