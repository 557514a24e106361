"""``position_friction`` -- Coulomb friction that varies along the travel (a worn screw section).

Model: in motion the friction magnitude in direction ``d`` is
``coulomb_d + g(x)``, and the breakaway levels rise by ``g(x)`` too, where
``g`` [command units] is a natural cubic spline through ``knots`` values
``f0 .. f{knots-1}`` at equally spaced positions from ``x_from`` to ``x_to``
[position units], held at its end values outside that range. It is smooth and
not periodic: a friction-over-position table as commissioning suites build
them. The Coulomb levels are the friction at ``x_from`` when ``f0 = 0`` (the
diagnosis fits it so; a constant added to every knot is a shift of both
Coulomb levels). Both levels plus ``g`` must stay >= 0 along the travel.

The spline is tabulated once and read by linear interpolation in the
integrator (sub-stepped, the level held over each sub-step).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    TableFriction,
    Terms,
    base_columns,
    base_fit,
    explained,
    regress,
    target,
)

#: Most knots of the spline (``sim://`` keys ``posfric_0`` .. ``posfric_7``).
MAX_KNOTS = 8
#: Fewest knots: two make a straight line over the travel.
MIN_KNOTS = 2
#: Points of the table the integrator interpolates.
TABLE_POINTS = 1024
#: Share of the samples beyond each end of the travel left out of the knot range.
TRAVEL_QUANTILE = 0.005
#: Knot counts above the screening's choice that go to the quick simulation.
EXTRA_KNOTS = 3
#: Fewer knots are kept while their held-out error is within this share of the best count's:
#: curves of different knot counts through one straight line differ by several percent there.
KNOT_TOLERANCE = 0.1

EFFECT = EffectSpec(
    name="position_friction",
    summary="Coulomb friction varying smoothly along the travel",
    params=(
        ParamSpec("x_from", "posfric_from", "units", "position of the first knot", default=None),
        ParamSpec("x_to", "posfric_to", "units", "position of the last knot", default=None),
        ParamSpec(
            "knots",
            "posfric_knots",
            "1",
            f"number of knots, {MIN_KNOTS} to {MAX_KNOTS}, equally spaced from x_from to x_to",
            MIN_KNOTS,
            MAX_KNOTS,
            default=None,
        ),
        *(
            ParamSpec(
                f"f{i}",
                f"posfric_{i}",
                "command units",
                f"friction added to both Coulomb levels at knot {i}",
                default=0.0,
            )
            for i in range(MAX_KNOTS)
        ),
    ),
    signature="the friction force differs along the travel in the same way in both directions "
    "of motion: the residual, signed by the direction of motion, is a smooth function of "
    "position (not periodic, unlike cogging, and not a force that pushes one way, unlike "
    "cogging or an offset)",
    fit="equation error with direction-signed spline regressors over the travelled range, the "
    "number of knots chosen on held-out samples, then simulation error on the knot values",
)


def knot_count(p) -> int:
    n = float(p["knots"])
    if n != int(n):
        raise UsageError(f"position_friction posfric_knots = {n:g} must be a whole number")
    return int(n)


def compact(p) -> dict[str, float]:
    """The parameters without the knots beyond ``knots`` (zero, unused: the library's defaults)."""
    n = knot_count(p)
    return {k: float(v) for k, v in p.items() if not (k[0] == "f" and int(k[1:]) >= n)}


def basis(x: np.ndarray, x_from: float, x_to: float, knots: int) -> np.ndarray:
    """Spline basis over ``x`` [units], shape ``(x.size, knots)``: column ``i`` is the natural
    cubic spline through 1 at knot ``i`` and 0 at the others, held constant outside the range."""
    from scipy.interpolate import CubicSpline

    nodes = np.linspace(x_from, x_to, knots)
    xc = np.clip(np.asarray(x, dtype=float), x_from, x_to)
    if knots == 2:
        t = (xc - x_from) / (x_to - x_from)
        return np.column_stack([1.0 - t, t])
    return CubicSpline(nodes, np.eye(knots), bc_type="natural")(xc)


def curve(p) -> tuple[float, float, np.ndarray]:
    """``(x_from, x_to, table)``: the spline ``g`` tabulated at :data:`TABLE_POINTS` points."""
    n = knot_count(p)
    x0, x1 = float(p["x_from"]), float(p["x_to"])
    if not x1 > x0:
        raise UsageError(f"position_friction needs posfric_to > posfric_from, got {x0:g}, {x1:g}")
    unused = [i for i in range(n, MAX_KNOTS) if float(p.get(f"f{i}", 0.0)) != 0.0]
    if unused:
        raise UsageError(f"position_friction posfric_{unused[0]} is set but posfric_knots = {n}")
    values = np.array([float(p[f"f{i}"]) for i in range(n)])
    return x0, x1, _table_basis(x0, x1, n) @ values


@lru_cache(maxsize=64)
def _table_basis(x_from: float, x_to: float, knots: int) -> np.ndarray:
    """The spline basis at the :data:`TABLE_POINTS` table points (kept: a refit builds the
    curve at every step with the same span and knots)."""
    out = basis(np.linspace(x_from, x_to, TABLE_POINTS), x_from, x_to, knots)
    out.setflags(write=False)
    return out


def check(p, plant) -> None:
    _, _, table = curve(p)
    lowest = float(table.min()) + min(plant.coulomb_pos, plant.coulomb_neg)
    if lowest < 0:
        raise UsageError(
            f"position_friction takes the friction below zero along the travel "
            f"(lowest level {lowest:.3g}): raise the knot values or the Coulomb levels"
        )


def contribute(p, plant, terms: Terms) -> None:
    x0, x1, table = curve(p)
    values = tuple(table.tolist())
    terms.friction_at = TableFriction(x0, (len(values) - 1) / (x1 - x0), values)


def travel(x: np.ndarray) -> tuple[float, float]:
    """The travelled range [units] the knots span (extreme samples trimmed)."""
    lo, hi = np.quantile(x, [TRAVEL_QUANTILE, 1.0 - TRAVEL_QUANTILE])
    if not hi > lo:
        lo, hi = float(np.min(x)), float(np.max(x))
    return float(lo), float(hi)


def _columns(ctx: ScreenInput, x_from: float, x_to: float, n: int) -> np.ndarray:
    """Direction-signed spline regressors on the moving samples, knot 0 left out (held at zero:
    a constant on every knot is a shift of both Coulomb levels)."""
    m = ctx.moving
    x, v = ctx.cat("x")[m], ctx.cat("v_f")[m]
    return np.sign(v)[:, None] * basis(x, x_from, x_to, n)[:, 1:]


def _fit(ctx: ScreenInput, x_from: float, x_to: float, n: int) -> tuple[np.ndarray, float]:
    """Base and knot coefficients on all moving samples, and the SSE."""
    return regress([*base_columns(ctx), *_columns(ctx, x_from, x_to, n).T], target(ctx))


def _knots_on_held_out(ctx: ScreenInput, x_from: float, x_to: float) -> int:
    """The fewest knots whose fit on the training samples predicts the held-out samples within
    :data:`KNOT_TOLERANCE` of the best knot count (a one-standard-error-like rule: a knot
    that does not pay clearly on held-out data is left out)."""
    y = target(ctx)
    cols = np.column_stack(base_columns(ctx))
    held = ctx.held_out[ctx.moving]
    train = ~held
    if held.sum() < 4 * MAX_KNOTS or train.sum() < 4 * MAX_KNOTS:
        held = train = np.ones(y.size, dtype=bool)
    sse = {}
    for n in range(MIN_KNOTS, MAX_KNOTS + 1):
        A = np.column_stack([cols, _columns(ctx, x_from, x_to, n)])
        coef, *_ = np.linalg.lstsq(A[train], y[train], rcond=None)
        resid = y[held] - A[held] @ coef
        sse[n] = float(resid @ resid)
    best = min(sse.values())
    return min(n for n, e in sse.items() if e <= (1.0 + KNOT_TOLERANCE) * best)


def _params(x_from: float, x_to: float, n: int, values) -> dict[str, float]:
    """The parameters of a curve of ``n`` knots (the unused knots left out)."""
    out = {"x_from": x_from, "x_to": x_to, "knots": float(n)}
    out.update({f"f{i}": float(values[i]) for i in range(n)})
    return out


def screen(ctx: ScreenInput) -> Screening:
    x = ctx.cat("x")[ctx.moving]
    y = target(ctx)
    coef0, sse0 = base_fit(ctx)
    fc = max(abs(coef0[2]), abs(coef0[3]), 1e-12)
    if x.size < 4 * MAX_KNOTS or not np.ptp(x) > 0:
        guess = _params(0.0, 1.0, MIN_KNOTS, [0.0, 0.0])
        return Screening(0.0, guess, {}, "no travel to vary along")
    x_from, x_to = travel(x)
    n = _knots_on_held_out(ctx, x_from, x_to)
    coef, sse = _fit(ctx, x_from, x_to, n)
    values = [0.0, *coef[4:]]
    guess = _params(x_from, x_to, n, values)
    # The equation error barely tells knot counts apart (the differentiated signals are
    # noisy); the simulation error does: curves of more knots go to the quick simulation and
    # the refit too, and the search keeps one only when it pays on held-out data (``order``).
    more = [
        _params(x_from, x_to, k, [0.0, *_fit(ctx, x_from, x_to, k)[0][4:]])
        for k in range(n + 1, min(n + EXTRA_KNOTS, MAX_KNOTS) + 1)
    ]
    top = max([float(np.max(np.abs(values)))] + [_largest(q) for q in more])
    span = 4.0 * max(fc, top)
    bounds = {f"f{i}": (-span, span) for i in range(1, MAX_KNOTS)}
    evidence = (
        "the friction changes along the travel in both directions of motion: a smooth curve "
        f"over position lowers the equation error by {100 * (1 - sse / sse0):.0f}% (its knots "
        "chosen on held-out samples)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    score = explained(sse0, sse, n - 1, y.size)
    return Screening(score, guess, bounds, evidence, base=base, alternatives=tuple(more))


def _largest(p) -> float:
    return max(abs(float(p[f"f{i}"])) for i in range(knot_count(p)))


def order(p) -> int:
    """The model order of a curve, its knot count: fits of different orders are chosen between
    on held-out data, not by their training error."""
    return knot_count(p)


def project(p, base):
    """Keep the friction above zero along the whole travel in both directions (for the refit):
    the curve's variation is scaled down until its lowest point clears the lower Coulomb level;
    the knots beyond the count are left out (unused: they are not fitted)."""
    floor = -0.95 * min(base["coulomb_pos"], base["coulomb_neg"])
    n = knot_count(p)
    p = {k: float(v) for k, v in p.items() if not (k[0] == "f" and int(k[1:]) >= n)}
    _, _, table = curve(p)
    lowest = float(table.min())
    if lowest >= floor:
        return dict(p)
    scale = floor / lowest if lowest < 0 else 0.0
    return {**p, **{f"f{i}": float(p[f"f{i}"]) * scale for i in range(n)}}


def describe(p) -> str:
    """The curve in words: where along the travel the friction is highest and lowest."""
    x0, x1, table = curve(p)
    grid = np.linspace(x0, x1, table.size)
    hi, lo = int(np.argmax(table)), int(np.argmin(table))
    return (
        f"friction {table[hi] - table[lo]:.3g} higher at x = {grid[hi]:.4g} than at "
        f"x = {grid[lo]:.4g} (spline with {knot_count(p)} knots over {x0:.4g} .. {x1:.4g})"
    )
