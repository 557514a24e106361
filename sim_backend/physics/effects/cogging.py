"""``cogging`` -- a force periodic in position (magnet cogging, screw pitch errors).

Model: a force ``amp * sin(2 pi x / period + phase)`` [command units] opposes
the command at motor position ``x`` [units]; ``period`` [units] > 0, ``phase``
[rad]. It also holds or releases the axis at rest: the body stays at rest
while ``|u - F_cog(x)|`` is within breakaway. Sub-stepped.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.sim_backend.physics.effects.spec import (
    EffectSpec,
    ParamSpec,
    Screening,
    ScreenInput,
    SineForce,
    Terms,
    base_columns,
    base_fit,
    explained,
    regress,
    target,
)

EFFECT = EffectSpec(
    name="cogging",
    summary="position-periodic force",
    params=(
        ParamSpec(
            "amp", "cog_amp", "command units", "amplitude of the periodic force", 0.0, default=None
        ),
        ParamSpec(
            "period", "cog_period", "units", "spatial period", 0.0, open_lower=True, default=None
        ),
        ParamSpec("phase", "cog_phase", "rad", "phase at x = 0", -100.0, 100.0, default=0.0),
    ),
    signature="the residual plotted against position repeats with a fixed spatial period, "
    "whatever the speed (a line in the periodogram of the force residual over position)",
    fit="periodogram of the equation error over position, its peak settled by the sin/cos "
    "regression with the base, then simulation error on amplitude, period and phase",
)


#: Spatial frequencies and samples of the screening periodogram (at most).
MAX_FREQUENCIES = 2000
PERIODOGRAM_SAMPLES = 6000
#: Frequencies of the refinement between two grid lines.
REFINE = 41
#: Divisors of the strongest spatial frequency also tried as the fundamental.
SUBHARMONICS = (2, 3)
#: Fewest periods over the travel searched, and accepted for a fundamental.
MIN_PERIODS = 3.0
MIN_PERIODS_FUNDAMENTAL = 1.5
#: Fewest periods over the travel of the long-period alternative, and its frequencies: wells
#: deeper than the breakaway trap the axis, which then travels only a period or two.
MIN_PERIODS_TRAPPED = 1.0
TRAPPED_FREQUENCIES = 60
#: Wells whose amplitude reaches this share of the smaller Coulomb level can hold the axis.
WELL_SHARE = 0.5
#: Frequencies of the periodogram between two fresh evaluations of each sample's ``exp(i k x)``.
PEAK_BLOCK = 64


def contribute(p, plant, terms: Terms) -> None:
    amp, phase = float(p["amp"]), float(p["phase"])
    k = 2.0 * math.pi / float(p["period"])
    terms.position_forces.append(SineForce(amp, k, phase))


def _peak(k_lo: float, k_hi: float, count: int, x: np.ndarray, e: np.ndarray) -> float:
    """Spatial frequency [rad/unit] among ``count`` evenly spaced from ``k_lo`` to ``k_hi`` where
    ``e`` has the most sin/cos power over the positions ``x``
    (:func:`~servobench.sim_backend.physics.periodogram.sincos_power`; imported here, so that a
    plant without effects never loads numba)."""
    from servobench.sim_backend.physics.periodogram import sincos_power

    ks = np.linspace(k_lo, k_hi, count)
    power = sincos_power(ks, np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(e, dtype=float), PEAK_BLOCK)
    return float(ks[int(np.argmax(power))])


#: The joint refinement's half-width, in periodogram grid lines.
JOINT_SPAN = 3.0


def _joint_peak(k: float, half: float, x: np.ndarray, cols: list, y: np.ndarray) -> float:
    """Spatial frequency [rad/unit] within ``half`` of ``k`` where the regression of ``y`` on
    the base columns and ``sin``/``cos(k x)`` leaves the least error: :data:`REFINE` lines,
    then as many between the best one's neighbours.

    The periodogram reads the base fit's residual, part of whose force the base columns have
    taken up (on a square wave the direction's column carries a share of the wells): its peak
    can sit a per cent off the period, a drift of a tenth of a period over eight.
    """
    # The base columns are the same at every frequency: regress once on their orthonormal basis
    # and fit each line's sine and cosine to what they leave (Frisch-Waugh-Lovell), all lines in
    # one batch, instead of a least-squares solve of all six columns per line.
    u, sv, _ = np.linalg.svd(np.column_stack(cols), full_matrices=False)
    q = u[:, sv > sv[0] * max(u.shape) * np.finfo(float).eps] if sv.size and sv[0] > 0 else u[:, :0]
    ry = y - q @ (q.T @ y)
    for _ in range(2):
        ks = np.linspace(k - half, k + half, REFINE)
        phase = np.outer(ks, x)
        rs, rc = (w - (w @ q) @ q.T for w in (np.sin(phase), np.cos(phase)))
        ss, sc, cc = (np.einsum("ij,ij->i", a, b) for a, b in ((rs, rs), (rs, rc), (rc, rc)))
        sy, cy = rs @ ry, rc @ ry
        det = ss * cc - sc * sc
        with np.errstate(divide="ignore", invalid="ignore"):
            gain = (cc * sy * sy - 2.0 * sc * sy * cy + ss * cy * cy) / det
        gain = np.where(det > 0, gain, 0.0)
        k, half = float(ks[int(np.argmax(gain))]), 2.0 * half / (REFINE - 1)
    return k


def screen(ctx: ScreenInput) -> Screening:
    m = ctx.moving
    x = ctx.cat("x")[m]
    y = target(ctx)
    cols = base_columns(ctx)
    coef0, sse0 = base_fit(ctx)
    e = y - np.column_stack(cols) @ coef0
    span = float(np.ptp(x)) if x.size else 0.0
    step = float(np.percentile(np.abs(np.diff(ctx.cat("x"))), 90)) if x.size > 1 else 0.0
    bounds0 = {"amp": (0.0, 1.0), "period": (1e-9, 1.0), "phase": (-4 * math.pi, 4 * math.pi)}
    if span <= 0 or step <= 0:
        return Screening(0.0, {"amp": 0.0, "period": 1.0, "phase": 0.0}, bounds0, "no travel")
    # Spatial frequencies from MIN_PERIODS periods over the travel to 6 samples per period.
    k_lo, k_hi = 2 * math.pi * MIN_PERIODS / span, 2 * math.pi / (6 * step)
    if k_hi <= k_lo:
        return Screening(
            0.0, {"amp": 0.0, "period": span, "phase": 0.0}, bounds0, "travel too short"
        )
    nk = int(min(MAX_FREQUENCIES, max(50, 4 * (k_hi - k_lo) * span / (2 * math.pi))))
    # The periodogram needs no more than a few thousand samples; the regression below uses all.
    pick = slice(None, None, max(1, x.size // PERIODOGRAM_SAMPLES))
    x_p, e_p = x[pick], e[pick]
    k = _peak(k_lo, k_hi, nk, x_p, e_p)
    # Refine on all samples between the neighbouring grid lines: a period off by a fraction of
    # a percent already drifts by a good part of a period over a long travel.
    step_k = (k_hi - k_lo) / (nk - 1)
    k = _peak(k - step_k, k + step_k, REFINE, x, e)
    k = _joint_peak(k, JOINT_SPAN * step_k, x, cols, y)

    def fit_at(k: float) -> tuple[dict[str, float], np.ndarray, float]:
        coef, sse = regress([*cols, np.sin(k * x), np.cos(k * x)], y)
        amp, phase = float(math.hypot(coef[4], coef[5])), float(math.atan2(coef[5], coef[4]))
        return {"amp": amp, "period": 2 * math.pi / k, "phase": phase}, coef, sse

    guess, coef, sse = fit_at(k)
    # Stick-slip puts harmonics into the residual: the strongest line may be the second or
    # third of the true period. Those fundamentals go to the quick simulation as alternatives.
    others = []
    for m in SUBHARMONICS:
        if k / m >= 2 * math.pi * MIN_PERIODS_FUNDAMENTAL / span:
            km = _peak(k / m - step_k, k / m + step_k, REFINE, x, e)
            others.append(fit_at(km)[0])
    k_trapped = 2 * math.pi * MIN_PERIODS_TRAPPED / span
    if k_trapped < k_lo:
        others.append(fit_at(_peak(k_trapped, k_lo, TRAPPED_FREQUENCIES, x, e))[0])
    period, amp = guess["period"], guess["amp"]
    longest = max([period] + [g["period"] for g in others])
    bounds = {
        "amp": (0.0, 4 * max([amp] + [g["amp"] for g in others]) + 1e-12),
        "period": (0.95 * period, 1.05 * longest),
        "phase": (-3 * math.pi, 3 * math.pi),
    }
    evidence = (
        f"the force residual repeats with position at a fixed spatial period "
        f"(equation error {100 * (1 - sse / sse0):.0f}% lower)"
    )
    base = {"M": coef[0], "B": coef[1], "coulomb_pos": coef[2], "coulomb_neg": coef[3]}
    score = explained(sse0, sse, 3, y.size)
    # Wells near the breakaway hold the axis: where it sticks, and so the rest of the run, turns
    # on where the wells lie (the phase: a few hundredths of a radian from the equation error's
    # can miss the basin), the amplitude and the base friction together -- a rugged surface,
    # scanned. Shallow ones (a screw's pitch error beside a large friction) are not: the
    # gradient refit suffices.
    breakaway = min(base["coulomb_pos"], base["coulomb_neg"])
    deep = max([amp] + [g["amp"] for g in others]) >= WELL_SHARE * breakaway
    return Screening(
        score,
        guess,
        bounds,
        evidence,
        base=base,
        scan=("phase", "amp") if deep else (),
        alternatives=tuple(others),
    )
