"""Inverse-dynamic least squares (IDIM-LS) on filtered signals, for logs with position only.

The position is filtered forward and backward and differentiated
(:mod:`servobench.bench.identify.derivative`); the command and the friction regressors are
filtered by the same filter in parallel, so the filter cancels from the
continuous-time relation::

    u_f = M a_f + B v_f + coulomb_pos * H[1(v > 0)] - coulomb_neg * H[1(v < 0)]

where ``H`` is the filter and ``u`` is taken at the sample instants as the
mean of the neighbouring zero-order holds. Samples near standstill (and the
filter's reach around them) are left out: while the axis sticks the friction
force is not ``±coulomb``. This is the estimator of the EMPS reference
(Janot et al.); it is consistent for closed-loop data with low-noise
position measurements.
"""

from __future__ import annotations

import math

import numpy as np

from servobench.bench.identify.dataset import Dataset, initial_velocity
from servobench.bench.identify.derivative import (
    differentiate_position,
    filter_command,
    lowpass,
    settle_samples,
)
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.identify.output_error import MAX_RAW_SAMPLES, Chunk, refine
from servobench.bench.model.servo import STD_KEYS, ServoModel
from servobench.errors import IdentificationError

#: Samples with |v| below this fraction of max |v| count as standstill.
REST_FRACTION = 1e-3
#: Time constants at the start of a run left out of the output-error comparison.
INITIAL_TIME_CONSTANTS = 10.0


def identify_idim(data: Dataset, *, refine_oe: bool = True) -> MethodEstimate:
    """``M``, ``B``, Coulomb friction per direction from position-only (derived-velocity) runs."""
    X, y, cutoff_hz = _regressors(data)
    theta, sd = _least_squares(X, y, data.fs_hz, cutoff_hz)
    M, B, fp, fn = (float(x) for x in theta)
    notes = list(data.notes)
    if fp < 0 or fn < 0:
        notes.append("a negative Coulomb level was estimated and clipped to 0")
    model = ServoModel(M, B, max(fp, 0.0), max(fn, 0.0))
    std = dict(zip(STD_KEYS, (float(x) for x in sd), strict=True))
    if data.closed_loop is not False or not refine_oe:
        if data.closed_loop:
            notes.append(
                "closed-loop log: inverse-dynamic least squares (IDIM-LS), no simulation-error refinement"
            )
        elif refine_oe:
            notes.append(
                "loop not stated in the log (metadata 'loop = open' enables the simulation-error "
                "refinement): inverse-dynamic least squares (IDIM-LS) only"
            )
        return MethodEstimate(model, "joint", std, "idim-ls", 0.0, tuple(notes))
    chunks = derived_chunks(data, model.time_constant_s)
    free = (True, True, bool(np.any(X[:, 2] > 0)), bool(np.any(X[:, 3] < 0)))
    oe = refine(model, chunks, free)
    return MethodEstimate(oe.model, "joint", oe.std, "idim-ls + output-error", 0.0, tuple(notes))


def _regressors(data: Dataset) -> tuple[np.ndarray, np.ndarray, float]:
    """Rows ``(a_f, v_f, H[v > 0], -H[v < 0])`` and targets ``u_f`` of the samples in clear
    motion, all runs stacked, and the filter cut-off [Hz]."""
    rows: list[np.ndarray] = []
    ys: list[np.ndarray] = []
    vmax = max(float(np.max(np.abs(s.v))) for s in data.segments)
    rest = REST_FRACTION * vmax
    fs = data.fs_hz
    cutoff = math.nan
    for s in data.segments:
        if s.motion is None:
            raise IdentificationError(
                "mixed logs (some runs with velocity, some without) are not supported"
            )
        cutoff = s.motion.cutoff_hz
        edge = settle_samples(fs, cutoff)
        if len(s) <= 2 * edge + 10:
            raise IdentificationError(
                f"run {s.run} is too short for the velocity filter ({len(s)} samples)"
            )
        v, a = s.motion.v, s.motion.a
        pos = (v > rest).astype(float)
        neg = (v < -rest).astype(float)
        still = ~((pos > 0) | (neg > 0))
        # the filter spreads a standstill over about fs/cutoff samples on each side
        reach = int(math.ceil(2.0 * fs / cutoff))
        near_still = np.convolve(still.astype(float), np.ones(2 * reach + 1), mode="same") > 0
        keep = ~near_still
        keep[:edge] = False
        keep[-edge:] = False
        uf = filter_command(s.u, fs, cutoff)
        hp = lowpass(pos, fs, cutoff)
        hn = lowpass(neg, fs, cutoff)
        rows.append(np.column_stack((a, v, hp, -hn))[keep])
        ys.append(uf[keep])
    X = np.concatenate(rows)
    y = np.concatenate(ys)
    if y.size < 10:
        raise IdentificationError("too few samples in motion for the inverse-dynamic fit")
    return X, y, cutoff


def _least_squares(
    X: np.ndarray, y: np.ndarray, fs_hz: float, cutoff_hz: float
) -> tuple[np.ndarray, np.ndarray]:
    """``theta = (M, B, coulomb_pos, coulomb_neg)`` and its 1-sigma, on scaled columns.

    Columns that are zero throughout (a direction never travelled) stay out: their
    parameter is 0 with an unknown (NaN) deviation. Filtered residuals are correlated
    over about ``fs / (2 cutoff)`` samples, which inflates the variance.
    """
    used = [i for i in range(4) if np.any(X[:, i] != 0)]
    Xu = X[:, used]
    scale = np.sqrt(np.mean(Xu * Xu, axis=0))
    scale[scale == 0] = 1.0
    theta_u, *_ = np.linalg.lstsq(Xu / scale, y, rcond=None)
    theta_u = theta_u / scale
    theta = np.zeros(4)
    theta[used] = theta_u
    r = y - X @ theta
    inflate = max(1.0, fs_hz / (2.0 * cutoff_hz))
    s2 = float(r @ r) / max(1, r.size - len(used)) * inflate
    sd = np.full(4, np.nan)
    try:
        cov = s2 * np.linalg.inv((Xu / scale).T @ (Xu / scale)) / np.outer(scale, scale)
        sd[used] = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        pass
    return theta, sd


def derived_chunks(data: Dataset, tau_s: float) -> list[Chunk]:
    """Raw windows whose simulated position is filtered and differentiated like the measurement.

    The derived velocity at a run's first sample is spoiled by the filter edge,
    so the first ``INITIAL_TIME_CONSTANTS * tau_s`` are left out of the comparison.
    """
    per_run = max(1, MAX_RAW_SAMPLES // len(data.segments))
    chunks = []
    for s in data.segments:
        seg = s.head(per_run) if len(s) > per_run else s
        if seg.x is None or seg.motion is None:
            raise IdentificationError(f"run {s.run} has no position to derive velocity from")
        # derive again on the window, so both sides see the same filter edges
        motion = differentiate_position(seg.x, data.fs_hz, seg.motion.cutoff_hz, seg.motion.method)
        v0 = initial_velocity(seg, 0.0)
        skip = max(
            settle_samples(data.fs_hz, motion.cutoff_hz),
            int(math.ceil(INITIAL_TIME_CONSTANTS * tau_s * data.fs_hz)),
        )
        if 2 * skip >= len(seg) - 10:
            raise IdentificationError(f"run {s.run} is too short for the output-error refinement")
        chunks.append(
            Chunk(seg.u, motion.v, data.dt_s, v0, skip=skip, derive=motion, x0=float(seg.x[0]))
        )
    return chunks
