"""The second body of a coupling effect: a spring-damper (resonance) or a play (backlash).

:class:`CouplingMixin` gives :class:`~servobench.sim_backend.physics.rich_plant.RichModel` its
two-body integrators; it reads the model's friction, segments, position
forces and hidden state.
"""

from __future__ import annotations

import functools

import numpy as np

from servobench.sim_backend.physics.bodies import Propagator, consts, friction_force, slider


@functools.lru_cache(maxsize=2048)
def spring_propagator(
    M: float, B_motor: float, B_load: float, r: float, k: float, d: float, held: bool
) -> Propagator:
    """The :class:`Propagator` of spring-coupled bodies: mass ``M`` [command units s^2/unit]
    shared ``1 - r`` : ``r`` between motor and load, the viscous coefficient of each body's
    direction (``B_motor``, ``B_load``) shared alike, a spring ``k`` and damper ``d`` between them
    (``held``: the motor stuck, the load alone). Models that differ only in friction or forces
    (most of a Jacobian's columns) share it."""
    Mm, Ml = (1 - r) * M, r * M
    Bm, Bl = (1 - r) * B_motor, r * B_load
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
    return Propagator(A, b)


class CouplingMixin:
    """Two-body integrators of :class:`~servobench.sim_backend.physics.rich_plant.RichModel`."""

    def _spring_system(self, sm: int, sl: int, held: bool) -> Propagator:
        """The spring-coupled bodies as ``dz/dt = A z + b w`` (cached per direction pair).

        State ``(vm, xm, vl, xl)`` with the force on the motor as input ``w``; ``held``:
        the motor is stuck and the load moves alone, state ``(vl, xl)``, input ``k xm``.
        """
        key = (sm, sl, held)
        hit = self._systems.get(key)
        if hit is not None:
            return hit
        c, p = self.terms.coupling, self.params
        Bm = self.B_pos if sm >= 0 else self.B_neg
        Bl = self.B_pos if sl >= 0 else self.B_neg
        out = self._systems[key] = spring_propagator(
            p.M, Bm, Bl, c.load_ratio, c.stiffness, c.damping, held
        )
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
        c = self.terms.coupling
        sl = 1 if s0[2] >= 0.0 else -1
        A, b = self._spring_step(th * h, sm, sl, False, cache=False)
        vm, xm, vl, xl = (
            sum(a * z for a, z in zip(row, s0, strict=True)) + bi * g
            for row, bi in zip(A, b, strict=True)
        )
        rest = (1.0 - th) * h
        net = f + c.stiffness * (xl - xm) + c.damping * vl
        F = friction_force(0.0, net, self.friction, xm)
        if F is None:
            (c00, c01), (c10, c11) = (A2 := self._spring_step(rest, 1, sl, True, cache=False))[0]
            d0, d1 = A2[1]
            w = c.stiffness * xm
            return 0.0, xm, c00 * vl + c01 * xl + d0 * w, c10 * vl + c11 * xl + d1 * w
        A, b = self._spring_step(rest, 1 if net > 0.0 else -1, sl, False, cache=False)
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
        fr, segs, pf = self.friction, self._segs, self._pos_force
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
                net = f + kk * (xl - xm) + cc * (vl - vm)
                F = friction_force(vm, net, fr, xm)
                if F is None:  # the motor is held: the load moves alone
                    (c00, c01), (c10, c11) = step(h, 1, sl, True)[0]
                    d0, d1 = step(h, 1, sl, True)[1]
                    w = kk * xm
                    vl, xl = c00 * vl + c01 * xl + d0 * w, c10 * vl + c11 * xl + d1 * w
                    continue
                sm = 1 if vm > 0.0 or (vm == 0.0 and net > 0.0) else -1
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

    def _gap_segments(self) -> list[tuple]:
        """Per segment of the interval: the constants the play's hot loop reads inline.

        ``(use_prev, h, rigid, motor, joint, alone, load_decay, load_gain)``: ``joint`` and
        ``alone`` are the coefficients of the engaged bodies and of the motor alone that
        their steppers were built from (prepared with the segments), so the inline steps
        give the steppers' numbers bit for bit.
        """
        return [
            (use_prev, h, rigid, motor, joint, alone, (kl[5], kl[6]), (kl[7], kl[8]))
            for (use_prev, h, rigid, motor, kl), (joint, alone) in zip(
                self._segs, self._inline, strict=True
            )
        ]

    def _run_gap(self, cur: list[float], prev: list[float], c) -> tuple[list, list]:
        """Motor (friction, forces) with a play of width ``gap`` to the load; sensor on the motor.

        Engaged, both move as one body and the contact force on the load is
        ``r (f - F_friction)``; the play opens when that force would pull.
        Closing it is an inelastic impact that conserves momentum.

        The hot path -- a body that keeps moving one way through a segment, with
        Coulomb friction only -- is the steppers' own arithmetic written inline
        (the diagnosis's refits run it tens of millions of times); sticking,
        reversals, impacts and velocity- or position-dependent friction go
        through :func:`slider` as before.
        """
        vm, xm, vl, xl, side = self._hidden
        fr, pf = self.friction, self._pos_force
        fcp, fcn = fr[0], fr[1]
        nfcn = -fcn
        # Coulomb levels alone, no position force: the inline steps apply.
        plain = fr[4] is None and fr[5] is None and pf is None
        r = c.load_ratio
        half = 0.5 * c.gap
        segs = self._gap_segments()
        vs: list[float] = []
        xs: list[float] = []
        push_v, push_x = vs.append, xs.append
        for uc, up in zip(cur, prev, strict=True):
            push_v(vm)
            push_x(xm)
            for use_prev, h, rigid, motor, joint, alone, (lap, lan), (lgp, lgn) in segs:
                f = up if use_prev else uc
                if pf is not None:
                    f -= pf(xm)
                if side:
                    # Friction the joint body would feel; the contact force is r (f - F).
                    if plain and vm != 0.0:  # friction_force of a moving body, inline
                        F = fcp if vm > 0.0 else nfcn
                    else:
                        F = friction_force(vm, f, fr, xm)
                    if F is not None and side * (f - F) < 0.0:
                        side = 0
                # One segment of the engaged bodies or of the motor alone: the slider's step,
                # inline while the body keeps moving one way.
                v0, x0, w0, y0 = vm, xm, vl, xl
                ap, an, gp, gn, Bp, Bn = joint if side else alone
                step = rigid if side else motor
                if plain and vm > 0.0:
                    vinf = (f - fcp) / Bp
                    vn = vinf + (vm - vinf) * ap
                    if vn > 0.0:
                        xm, vm = xm + vinf * h + (vm - vinf) * gp, vn
                    else:
                        vm, xm = step(vm, xm, f)
                elif plain and vm < 0.0:
                    vinf = (f - nfcn) / Bn
                    vn = vinf + (vm - vinf) * an
                    if vn < 0.0:
                        xm, vm = xm + vinf * h + (vm - vinf) * gn, vn
                    else:
                        vm, xm = step(vm, xm, f)
                else:
                    vm, xm = step(vm, xm, f)
                if side:
                    vl, xl = vm, xm - side * half
                    continue
                if vl >= 0.0:
                    xl += vl * lgp
                    vl *= lap
                else:
                    xl += vl * lgn
                    vl *= lan
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
                        k_rest = consts(rest, self.params.M, self.B_pos, self.B_neg)
                        vm, xm = slider(k_rest, fr)(vi, xi, f)
                    else:
                        vm, xm = vi, xi
                    vl, xl = vm, xm - side * half
        self._hidden = (vm, xm, vl, xl, side)
        return vs, xs
