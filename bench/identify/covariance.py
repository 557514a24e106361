"""Parameter covariances that hold when the residual is not white: HAC sandwich and whiteness test.

A least-squares estimate ``theta`` of residuals ``r(theta)`` with Jacobian ``J``
has, to first order, the error ``-(J^T J)^-1 J^T e``. The textbook covariance
``s^2 (J^T J)^-1`` assumes ``e`` white. Coloured noise (a velocity filter, a
sensor with its own dynamics), rounding tied to the signal, or an effect the
model lacks make ``e`` correlated in time, and that covariance then states far
too small a sigma (a 10-sample AR(1) correlation: about 4x too small).

:func:`hac_covariance` is the sandwich ``(J^T J)^-1 S (J^T J)^-1`` with ``S``
the long-run covariance of the scores ``g_t = J_t r_t`` by Newey-West with the
Parzen kernel (positive semi-definite), lags never crossing from one segment of
data into another. The bandwidth follows the residual: Andrews' (1991) AR(1)
plug-in from its lag-1 autocorrelation, doubled (the plug-in minimises the mean
squared error of ``S``, which leaves it a few per cent small at strong
correlation; a sigma must not be), so white residuals get a few lags and the
sandwich is then White's, close to the textbook covariance.

:func:`residual_colour` tests the residual for whiteness (Ljung-Box over
:data:`LJUNG_BOX_LAGS` lags, pooled over the segments): what the notes of a
result say when the residual is coloured.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

#: Lags of the Ljung-Box whiteness test.
LJUNG_BOX_LAGS = 20
#: A residual whose Ljung-Box p-value falls below this is called coloured.
WHITENESS_P = 1e-3
#: The lag-1 autocorrelation the bandwidth plug-in is given is clipped to this magnitude.
MAX_RHO = 0.98
#: Factor on Andrews' plug-in bandwidth (see the module docstring).
BANDWIDTH_FACTOR = 2.0
#: Fewest samples per lag: the bandwidth stays below this fraction of the longest segment.
MAX_BANDWIDTH_SHARE = 0.25
#: Highest order of the noise's autoregression (:func:`noise_model_covariance`).
AR_MAX_ORDER = 20
#: Fits of the noise model where a start's noise is taken out of the residual (each weighs
#: that with the model before it).
START_PASSES = 2


@dataclass(frozen=True)
class ResidualColour:
    """Whiteness of a residual.

    Attributes
    ----------
    rho1 : float
        Lag-1 autocorrelation (pooled over the segments).
    q : float
        Ljung-Box statistic over ``lags`` lags.
    p_value : float
        Its p-value under white noise (chi-square with ``lags`` degrees of freedom).
    lags : int
    coloured : bool
        ``p_value < WHITENESS_P``.
    """

    rho1: float
    q: float
    p_value: float
    lags: int
    coloured: bool

    def note(self, what: str, by: str = "a HAC (Newey-West) covariance") -> str:
        """One line for a result's notes: what was found and what the sigmas allow for it ``by``."""
        p = "< 1e-12" if self.p_value < 1e-12 else f"{self.p_value:.1g}"
        return (
            f"{what} residual is coloured (lag-1 autocorrelation {self.rho1:.2f}, Ljung-Box p {p}): "
            f"its 1-sigma come from {by} that allows for it"
        )


def _segments(n: int, bounds: Sequence[int] | None) -> list[tuple[int, int]]:
    """``(start, stop)`` of each segment from the cumulative ``bounds`` (ends), all of ``n`` by default."""
    if bounds is None or len(bounds) == 0:
        return [(0, n)]
    out, start = [], 0
    for stop in bounds:
        if stop > start:
            out.append((start, int(stop)))
        start = int(stop)
    if start < n:
        out.append((start, n))
    return out


def _autocorrelation(r: np.ndarray, segments: list[tuple[int, int]], lags: int) -> np.ndarray:
    """Pooled autocorrelation of ``r`` at lags ``1 .. lags`` (each within its segment)."""
    r = np.asarray(r, dtype=float)
    c0 = float(r @ r)
    out = np.zeros(lags)
    if c0 <= 0.0:
        return out
    for k in range(1, lags + 1):
        out[k - 1] = sum(float(r[a + k : b] @ r[a : b - k]) for a, b in segments if b - a > k) / c0
    return out


def residual_colour(r: np.ndarray, bounds: Sequence[int] | None = None, lags: int = LJUNG_BOX_LAGS) -> ResidualColour:
    """Ljung-Box whiteness test of ``r`` (segments ending at ``bounds``, lags within each)."""
    from scipy.special import chdtrc  # chi2.sf itself, without importing scipy.stats (0.3-0.6 s)

    r = np.asarray(r, dtype=float)
    n = r.size
    segments = _segments(n, bounds)
    lags = max(1, min(lags, max(1, n // 4)))
    rho = _autocorrelation(r - np.mean(r), segments, lags)
    k = np.arange(1, lags + 1)
    q = float(n * (n + 2) * np.sum(rho**2 / np.maximum(n - k, 1)))
    p = float(chdtrc(lags, q))
    return ResidualColour(float(rho[0]), q, p, lags, p < WHITENESS_P)


def bandwidth(r: np.ndarray, bounds: Sequence[int] | None = None) -> int:
    """Parzen bandwidth [lags] for the long-run covariance of ``r``'s scores (see module docstring)."""
    r = np.asarray(r, dtype=float)
    segments = _segments(r.size, bounds)
    rho = float(np.clip(_autocorrelation(r, segments, 1)[0], -MAX_RHO, MAX_RHO))
    alpha = 4.0 * rho**2 / (1.0 - rho) ** 4
    lags = BANDWIDTH_FACTOR * 2.6614 * (alpha * r.size) ** 0.2
    longest = max(b - a for a, b in segments)
    return int(max(1, min(math.ceil(lags), int(MAX_BANDWIDTH_SHARE * longest))))


def parzen(x: np.ndarray) -> np.ndarray:
    """The Parzen lag window on ``|x| <= 1`` (0 beyond)."""
    x = np.abs(np.asarray(x, dtype=float))
    return np.where(x <= 0.5, 1.0 - 6.0 * x**2 + 6.0 * x**3, np.where(x <= 1.0, 2.0 * (1.0 - x) ** 3, 0.0))


def long_run_covariance(g: np.ndarray, bounds: Sequence[int] | None, lags: int) -> np.ndarray:
    """``sum_t sum_s k((t - s)/lags) g_t g_s^T`` over pairs in the same segment (Parzen ``k``)."""
    g = np.asarray(g, dtype=float)
    segments = _segments(g.shape[0], bounds)
    S = g.T @ g
    weights = parzen(np.arange(1, max(lags, 1)) / lags).tolist()  # one call, not one per lag
    for k, w in enumerate(weights, start=1):
        if w == 0.0:
            break
        G = np.zeros_like(S)
        for a, b in segments:
            if b - a > k:
                G += g[a + k : b].T @ g[a : b - k]
        S += w * (G + G.T)
    return S


def _on_moved(J: np.ndarray, covariance: Callable[[np.ndarray], np.ndarray]) -> np.ndarray | None:
    """Where some column of ``J`` is zero (a parameter the residual does not move at all):
    ``covariance`` of the other columns, NaN rows and columns for those; None where the residual
    moves every parameter."""
    moved = np.any(J != 0.0, axis=0)
    if moved.all():
        return None
    p = J.shape[1]
    out = np.full((p, p), np.nan)
    if moved.any():
        out[np.ix_(moved, moved)] = covariance(J[:, moved])
    return out


def hac_covariance(
    jac: np.ndarray, r: np.ndarray, bounds: Sequence[int] | None = None, lags: int | None = None
) -> np.ndarray:
    """Covariance of a least-squares estimate robust to correlated residuals.

    Parameters
    ----------
    jac : ndarray, shape (n, p)
        Jacobian of the residual with respect to the parameters, at the estimate.
    r : ndarray, shape (n,)
        Residual at the estimate (the same weighting as ``jac``).
    bounds : sequence of int, optional
        Ends of the segments of ``r`` (lags never cross from one to the next);
        one segment by default.
    lags : int, optional
        Bandwidth; by default :func:`bandwidth`.

    Returns
    -------
    ndarray, shape (p, p)
        ``(J^T J)^-1 S (J^T J)^-1 n / (n - p)``. A parameter the residual does not move at all
        (its column zero) is undetermined: its row and column are NaN, the others' covariance
        stands without it; NaN throughout where ``J^T J`` is singular otherwise.
    """
    J = np.asarray(jac, dtype=float)
    r = np.asarray(r, dtype=float)
    n, p = J.shape
    partial = _on_moved(J, lambda moved: hac_covariance(moved, r, bounds, lags))
    if partial is not None:
        return partial
    if lags is None:
        lags = bandwidth(r, bounds)
    try:
        H_inv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.nan)
    S = long_run_covariance(J * r[:, None], bounds, lags)
    return H_inv @ S @ H_inv * (n / max(1, n - p))


def _valid_autocovariance(
    r: np.ndarray, valid: np.ndarray, segments: list[tuple[int, int]], lags: int
) -> np.ndarray:
    """Autocovariance of ``r`` at lags ``0 .. lags`` over the pairs of valid samples within one
    segment (each lag's sum over its own number of pairs)."""
    rv = np.where(valid, r, 0.0)
    m = valid.astype(float)
    total, pairs = np.zeros(lags + 1), np.zeros(lags + 1)
    for a, b in segments:
        for k in range(min(lags, b - a - 1) + 1):
            total[k] += float(rv[a + k : b] @ rv[a : b - k])
            pairs[k] += float(m[a + k : b] @ m[a : b - k])
    return np.divide(total, pairs, out=np.zeros_like(total), where=pairs > 0)


def autoregression(rho: np.ndarray, n: int, max_order: int = AR_MAX_ORDER) -> np.ndarray:
    """Coefficients ``phi`` of the autoregression ``e_t = sum_i phi_i e_{t-i} + w_t`` of least
    AIC (``n log var(w) + 2 order``, order ``0 .. max_order``) for the autocorrelation ``rho``
    (lags ``0 .. max_order``), by Levinson-Durbin; empty for white noise."""
    phi, best, best_aic, v = np.zeros(0), np.zeros(0), 0.0, 1.0
    for p in range(1, min(max_order, rho.size - 1) + 1):
        k = (rho[p] - float(phi @ rho[p - 1 : 0 : -1])) / v
        if not abs(k) < 1.0:
            break
        phi = np.append(phi - k * phi[::-1], k)
        v *= 1.0 - k * k
        aic = n * math.log(v) + 2.0 * p
        if aic < best_aic:
            best, best_aic = phi.copy(), aic
    return best


def ar_autocorrelation(phi: np.ndarray, rho: np.ndarray, lags: int) -> np.ndarray:
    """The autocorrelation at lags ``0 .. lags`` of the autoregression ``phi`` whose first
    ``len(phi) + 1`` values are ``rho`` (what Yule-Walker matches), on by its recursion."""
    p = phi.size
    out = np.zeros(lags + 1)
    out[: min(p, lags) + 1] = rho[: min(p, lags) + 1]
    if p == 0:
        return out
    for k in range(p + 1, lags + 1):
        out[k] = float(phi @ out[k - 1 : k - p - 1 : -1])  # out[k-1] .. out[k-p]
        if k > 4 * p and np.all(np.abs(out[k - p : k + 1]) < 1e-9):
            break  # decayed: the rest are zero to the precision that matters
    return out


def _without_start(
    r: np.ndarray, gain: np.ndarray, segments: list[tuple[int, int]], phi: np.ndarray
) -> np.ndarray:
    """``r`` less, in each segment, the multiple of ``gain`` that least-squares fits it after
    both are whitened by the autoregression ``phi``."""
    from scipy.signal import lfilter

    out = r.copy()
    whiten = np.concatenate(([1.0], -phi))
    for a, b in segments:
        h = gain[a:b]
        if not float(h @ h) > 0.0:
            continue
        wh, wr = lfilter(whiten, [1.0], h), lfilter(whiten, [1.0], r[a:b])
        out[a:b] -= float(wh @ wr) / float(wh @ wh) * h
    return out


def noise_model_covariance(
    jac: np.ndarray,
    r: np.ndarray,
    bounds: Sequence[int] | None = None,
    valid: np.ndarray | None = None,
    start_gain: np.ndarray | None = None,
    max_order: int = AR_MAX_ORDER,
) -> np.ndarray:
    """Covariance of a least-squares estimate whose residual is stationary noise within each
    segment, its autocovariance from an autoregression fitted to the residual.

    Parameters
    ----------
    jac : ndarray, shape (n, p)
        Jacobian of the residual at the estimate; rows of samples not in the cost are zero.
    r : ndarray, shape (n,)
        Residual at the estimate (the same weighting as ``jac``).
    bounds : sequence of int, optional
        Ends of the segments (the noise of one is independent of the others'); one by default.
    valid : ndarray of bool, shape (n,), optional
        Samples in the cost (all by default): the autocovariance is taken over pairs of them,
        at their true lags, so samples left out of a segment do not shorten them.
    start_gain : ndarray, shape (n,), optional
        How much the model output at each sample moves with the noise of its segment's first
        sample (a simulation started from that sample's measured value; 0 where it starts from
        a fixed state). That noise enters the estimate through ``jac``'s products with it.
    max_order : int
        Highest order of the autoregression (:func:`autoregression`).

    Returns
    -------
    ndarray, shape (p, p)
        ``(J^T J)^-1 A^T Sigma A (J^T J)^-1 n / (n - p)``, ``A`` the Jacobian with the start
        noise's loading added to each segment's first row, ``Sigma`` the noise's block Toeplitz
        covariance, ``n`` the valid samples. Columns the residual does not move are NaN, as in
        :func:`hac_covariance`.
    """
    from scipy.signal import fftconvolve

    J = np.asarray(jac, dtype=float)
    r = np.asarray(r, dtype=float)
    n_rows, p = J.shape
    partial = _on_moved(
        J, lambda moved: noise_model_covariance(moved, r, bounds, valid, start_gain, max_order)
    )
    if partial is not None:
        return partial
    valid = np.ones(n_rows, dtype=bool) if valid is None else np.asarray(valid, dtype=bool)
    n = int(valid.sum())
    segments = _segments(n_rows, bounds)
    h = None if start_gain is None else np.where(valid, np.asarray(start_gain, dtype=float), 0.0)
    if h is not None and not h.any():
        h = None  # every window starts from a fixed state: no start noise to take out
    phi = np.zeros(0)
    for _ in range(START_PASSES if h is not None else 1):
        # the residual holds each start sample's noise times the gain: a decay, not the
        # noise's colour; the noise model is fitted with it taken out (by least squares
        # weighted with the noise model so far: unweighted, it takes the coloured noise's
        # slow part with it)
        noise = r if h is None else _without_start(r, h, segments, phi)
        gamma = _valid_autocovariance(noise, valid, segments, max_order)
        if not gamma[0] > 0.0:
            return np.zeros((p, p))
        rho = gamma / gamma[0]
        phi = autoregression(rho, n, max_order)
    acf = ar_autocorrelation(phi, rho, max(b - a for a, b in segments) - 1)
    try:
        H_inv = np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return np.full((p, p), np.nan)
    A = J.copy()
    if h is not None:
        for a, b in segments:
            A[a] -= h[a:b] @ J[a:b]
    S = np.zeros((p, p))
    for a, b in segments:
        L = b - a
        two_sided = np.concatenate((acf[L - 1 : 0 : -1], acf[:L]))
        SA = fftconvolve(A[a:b], two_sided[:, None], mode="full", axes=0)[L - 1 : 2 * L - 1]
        S += A[a:b].T @ SA
    S = 0.5 * (S + S.T) * gamma[0]
    return H_inv @ S @ H_inv * (n / max(1, n - p))
