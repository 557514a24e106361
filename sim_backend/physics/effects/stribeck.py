"""``stribeck`` -- friction that is higher at low speed than the Coulomb level.

Model: in motion the friction magnitude in direction ``d`` is
``fc_d + (fs - fc_d) * exp(-(|v| / vs)^2)``; at rest the axis breaks away at
``fs``. ``fs`` [command units] is the static level (>= both Coulomb levels),
``vs`` [units/s] the Stribeck velocity. The friction depends on velocity
inside an interval, so the integrator sub-steps (about ``vs / 4`` of velocity
change per sub-step).
"""

from __future__ import annotations

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    GaussianExcess,
    ParamSpec,
    Screening,
    ScreenInput,
    Terms,
    base_columns,
    base_values,
    explained,
    target,
)

EFFECT = EffectSpec(
    name="stribeck",
    summary="friction rising towards a static level at low speed",
    params=(
        ParamSpec("fs", "stribeck_fs", "command units", "static friction level", 0.0, default=None),
        ParamSpec(
            "vs", "stribeck_vs", "units/s", "Stribeck velocity", 0.0, open_lower=True, default=None
        ),
    ),
    signature="the residual force is largest just after each start and reversal and decays "
    "with speed over a characteristic velocity: friction falls from a static to the Coulomb level",
    fit="equation error with a sign(v)*exp(-(v/vs)^2) regressor over a grid of vs, then "
    "simulation error on fs and vs together with the base",
)


#: Largest static excess over Coulomb the screening accepts, in Coulomb levels.
MAX_EXCESS = 5.0
#: Smallest viscous coefficient of the screening fits, as a share of rms(u) / rms(v).
B_FLOOR = 0.01


def check(p, plant) -> None:
    if p["fs"] < max(plant.coulomb_pos, plant.coulomb_neg):
        raise UsageError(
            f"stribeck_fs = {p['fs']:g} must be at least the Coulomb levels "
            f"({plant.coulomb_pos:g}, {plant.coulomb_neg:g})"
        )


def contribute(p, plant, terms: Terms) -> None:
    fs, vs = float(p["fs"]), float(p["vs"])
    dp, dn = fs - plant.coulomb_pos, fs - plant.coulomb_neg
    terms.friction_excess = GaussianExcess(dp, dn, 1.0 / vs)
    terms.static_pos = max(terms.static_pos, fs)
    terms.static_neg = max(terms.static_neg, fs)
    drop = max(dp, dn, 1e-12)
    terms.substep_s = min(terms.substep_s, 0.25 * plant.M * vs / drop)


def _spread(coef0: np.ndarray, scale: float) -> tuple[dict[str, float], ...]:
    """Static levels and Stribeck velocities for a quick simulation to judge: most of the
    Stribeck curve lives at speeds the inverse-dynamics equation leaves out."""
    fc = max(coef0[2], coef0[3], 1e-12)
    return tuple(
        {"fs": float(fc * level), "vs": float(scale * speed)}
        for level in (1.4, 1.8, 2.4)
        for speed in (0.04, 0.08, 0.16)
    )


#: Breakaway restarts: the current base's Coulomb level taken as the static level, the
#: Coulomb level divided by each of these ...
BREAKAWAY_LEVELS = (2.0, 3.0, 4.5)
#: ... the Stribeck velocity at each of these shares of the top speed (99th percentile) ...
BREAKAWAY_SPEEDS = (0.25, 0.5)
#: ... and a viscous coefficient whose force at the top speed is this share of the command's
#: amplitude above the new Coulomb level.
BREAKAWAY_VISCOUS = 0.5
#: The restarts are offered only where the base's viscous force at the top speed is under this
#: share of its Coulomb level (a viscous coefficient near zero: their signature).
BREAKAWAY_BELOW = 0.1


def _breakaway(ctx: ScreenInput) -> tuple[tuple[dict[str, float], dict[str, float]], ...]:
    """Starts for an axis that mostly sticks: a base fitted on it puts its Coulomb level at the
    breakaway and its viscous coefficient near zero (what little motion there is stays below
    the Stribeck velocity), and no Stribeck curve over that level moves it at all. Each start
    keeps that level as the static one, lowers the Coulomb levels under it, and gives the
    motion a viscous coefficient that bounds its speed near the speed seen."""
    base = base_values(ctx)
    static = max(base["coulomb_pos"], base["coulomb_neg"])
    top = float(np.percentile(np.abs(ctx.cat("v")), 99))
    amplitude = float(np.max(np.abs(ctx.cat("u"))))
    if not (static > 0 and top > 0 and amplitude > static and base["M"] > 0):
        return ()
    if base["B"] * top >= BREAKAWAY_BELOW * static:  # the base moves with viscous friction
        return ()
    out = []
    for level in BREAKAWAY_LEVELS:
        coulomb = static / level
        viscous = BREAKAWAY_VISCOUS * (amplitude - coulomb) / top
        start = {
            **base,
            "B": viscous,
            "coulomb_pos": base["coulomb_pos"] / level,
            "coulomb_neg": base["coulomb_neg"] / level,
        }
        out += [(start, {"fs": static, "vs": share * top}) for share in BREAKAWAY_SPEEDS]
    return tuple(out)


def bounded_fit(
    columns: list[np.ndarray], y: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, float]:
    """Least squares of ``y`` on ``columns`` within bounds; coefficients and residual SSE."""
    from scipy.optimize import lsq_linear

    A = np.column_stack(columns)
    q, r = np.linalg.qr(A)
    qty = q.T @ y
    sol = lsq_linear(r, qty, bounds=(lower, upper), method="bvls")
    rest = max(float(y @ y - qty @ qty), 0.0)  # what no combination of the columns reaches
    miss = r @ sol.x - qty
    return sol.x, rest + float(miss @ miss)


def screen(ctx: ScreenInput) -> Screening:
    m = ctx.moving
    v = ctx.cat("v_f")[m]
    y = target(ctx)
    cols = base_columns(ctx)
    speed = np.abs(v)
    scale = float(np.sqrt(np.mean(v * v))) or 1.0
    # Viscous friction is not negative: a base fit that wants it so is the signature of
    # friction falling with speed, and the curve is fitted with B held at or above a floor.
    b_min = B_FLOOR * float(np.sqrt(np.mean(y * y))) / scale
    inf = np.inf
    coef0, sse0 = bounded_fit(cols, y, np.array([0, b_min, 0, 0]), np.array([inf] * 4))
    # Friction levels beyond a few times the Coulomb level are not a Stribeck curve but a
    # regressor that vanishes on the moving samples.
    ceiling = MAX_EXCESS * max(abs(coef0[2]), abs(coef0[3]), 1e-12)
    lower, upper = np.array([0, b_min, 0, 0, 0]), np.array([inf, inf, inf, inf, ceiling])
    slowest = float(np.min(speed)) if speed.size else 0.0
    best = None
    for vs in scale * np.geomspace(0.01, 1.0, 40):
        if vs < 0.5 * slowest:
            continue
        col = np.sign(v) * np.exp(-((speed / vs) ** 2))
        coef, sse = bounded_fit([*cols, col], y, lower, upper)
        if coef[4] > 0 and (best is None or sse < best[0]):
            best = (sse, vs, coef)
    bounds = {
        "fs": (0.0, 10.0 * max(abs(coef0[2]), abs(coef0[3]), 1e-9)),
        "vs": (0.02 * scale, 3 * scale),
    }
    if best is None:
        fc = max(coef0[2], coef0[3], 0.0)
        guess = {"fs": 1.5 * fc, "vs": 0.1 * scale}
        return Screening(
            0.0,
            guess,
            bounds,
            "no friction excess at low speed",
            alternatives=_spread(coef0, scale),
            restarts=_breakaway(ctx),
        )
    sse, vs, coef = best
    fcp, fcn = max(coef[2], 0.0), max(coef[3], 0.0)
    fs = 0.5 * (fcp + fcn) + coef[4]
    fs = max(fs, fcp, fcn)
    bounds["fs"] = (0.0, max(bounds["fs"][1], 3 * fs))
    evidence = (
        f"friction rises at low speed: the force residual follows a Stribeck curve "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": fcp, "coulomb_neg": fcn}
    score = explained(sse0, sse, 2, y.size)
    return Screening(
        score,
        {"fs": fs, "vs": vs},
        bounds,
        evidence,
        base=base,
        alternatives=_spread(coef0, scale),
        restarts=_breakaway(ctx),
    )


def project(p, base):
    """Keep the static level at or above both Coulomb levels (for the refit)."""
    return {**p, "fs": max(p["fs"], base["coulomb_pos"], base["coulomb_neg"])}
