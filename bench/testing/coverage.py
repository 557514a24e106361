"""Do the stated 1-sigma cover the error? SIDBE pairs of the simulated drive with known noise.

The lock-step simulated drive (``sim://``: M = 0.1, B = 1, Coulomb 0.5 / 0.4, no
delay unless one is given) runs the SIDBE excitation once without noise (:func:`clean_log`); each
case adds velocity-sensor noise of one kind to that log and identifies it
(:func:`coverage_case`). In open loop the command does not depend on what is
measured, so this is the log the drive would have written with that noise, and
one clean run serves every seed. The noise kinds (:data:`NOISE_KINDS`):

``white``
    white Gaussian noise of 1-sigma :data:`WHITE_STD`, as ``sim://?noise=0.02``;
``coloured``
    AR(1) noise ``e[k] = rho e[k-1] + w[k]``, ``rho`` = :data:`AR_RHO` (a 10-sample
    correlation time at 1 kHz), stationary 1-sigma :data:`WHITE_STD`;
``quantised``
    white noise of 1-sigma :data:`QUANT_NOISE_STD`, then rounded to steps of
    :data:`QUANT_STEP` (as ``sim://?noise=0.01&res_v=0.02``): the rounding error is
    tied to the signal and not Gaussian.

:func:`summarise` gives, per parameter, the rms of error over sigma (1 when the
sigmas are honest) and the shares within 1 and 2 sigma (68 % and 95 %).

The identified delay cannot be negative: where the drive has none, the truth
sits on that bound, half the errors are 0 and the other half one-sided, and an
honest sigma gives an rms of about 0.71 and 97.7 % within 2 sigma, not 1.0 and
95 %. A drive delay inside the range (``delay_s``: the plant's ``time_delay``,
``sim://?delay=S``) judges the delay's sigma where the Gaussian figures apply.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from servobench.bench.log.io import ExperimentLog, read_log

#: The parameters whose sigma is checked, in the order printed.
PARAMETERS = ("M", "B", "coulomb_pos", "coulomb_neg", "delay_s")
#: The plant of ``sim://`` (its defaults) and the drive's delay (none).
TRUTH = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4, "delay_s": 0.0}
#: The noise kinds :func:`noisy_log` adds.
NOISE_KINDS = ("white", "coloured", "quantised")
#: 1-sigma of the white and of the coloured noise [rad/s].
WHITE_STD = 0.02
#: AR(1) coefficient of the coloured noise (per 1 ms sample).
AR_RHO = 0.9
#: Quantised kind: the noise before rounding [rad/s] and the rounding step [rad/s].
QUANT_NOISE_STD = 0.01
QUANT_STEP = 0.02
#: The clean drive: default plant, no noise.
CLEAN_URL = "sim://?seed=0"


def clean_log(
    out: str | Path, *, periods: int = 4, period_s: float = 4.0, delay_s: float = 0.0
) -> ExperimentLog:
    """The noise-free SIDBE log of the simulated drive (one round), written under ``out``; the
    plant delays the command by ``delay_s`` [s] (its ``time_delay``)."""
    import servobench as sb

    url = CLEAN_URL + (f"&delay={delay_s!r}" if delay_s else "")
    with sb.open_drive(url) as drive:
        sb.sidbe(drive, out=str(out), periods=periods, period_s=period_s, max_iterations=1, plots=False)
    return read_log(Path(out) / "log.csv")


def noise(kind: str, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` samples of measurement noise of ``kind`` (before any rounding) [rad/s]."""
    if kind == "white":
        return rng.normal(0.0, WHITE_STD, n)
    if kind == "coloured":
        from scipy.signal import lfilter

        w = rng.normal(0.0, WHITE_STD * math.sqrt(1.0 - AR_RHO**2), n)
        e0 = rng.normal(0.0, WHITE_STD)  # the stationary start
        return lfilter([1.0], [1.0, -AR_RHO], w, zi=[AR_RHO * e0])[0]
    if kind == "quantised":
        return rng.normal(0.0, QUANT_NOISE_STD, n)
    raise ValueError(f"unknown noise kind {kind!r}; choose from {', '.join(NOISE_KINDS)}")


def noisy_log(clean: ExperimentLog, kind: str, seed: int) -> ExperimentLog:
    """``clean`` with velocity noise of ``kind`` drawn from ``seed`` (each run its own draw)."""
    rng = np.random.default_rng([seed, NOISE_KINDS.index(kind)])
    runs = []
    for r in clean.runs:
        assert r.v is not None
        v = r.v + noise(kind, r.v.size, rng)
        if kind == "quantised":
            v = np.round(v / QUANT_STEP) * QUANT_STEP
        runs.append(replace(r, v=v))
    return replace(clean, runs=tuple(runs), source=f"{kind} seed {seed}")


def coverage_case(
    clean: ExperimentLog, kind: str, seed: int, method: str = "auto", delay_s: float = 0.0
) -> dict[str, object]:
    """Identify one noisy log: per parameter the error and the stated sigma, and the estimator
    (``delay_s``: the delay of the plant ``clean`` was run on [s])."""
    from servobench.bench.identify.auto import identify

    result = identify(noisy_log(clean, kind, seed), method)
    values = {**{k: getattr(result.model, k) for k in PARAMETERS[:4]}, "delay_s": result.model.delay_s}
    truth = {**TRUTH, "delay_s": delay_s}
    return {
        "kind": kind,
        "seed": seed,
        "estimator": f"{result.method}/{result.estimator}",
        "error": {k: float(values[k] - truth[k]) for k in PARAMETERS},
        "std": {k: float(result.std.get(k, math.nan)) for k in PARAMETERS},
        "notes": list(result.notes),
    }


def summarise(cases: Iterable[Mapping[str, object]], parameters: Sequence[str] = PARAMETERS) -> dict[str, dict[str, float]]:
    """Per parameter: ``rms`` of error/sigma, shares ``within1`` and ``within2`` sigma, and ``n``.

    A case whose sigma is missing, zero or not finite counts as outside both
    bands and is left out of the rms (``unstated`` counts it).
    """
    cases = list(cases)
    out = {}
    for key in parameters:
        z, unstated = [], 0
        for c in cases:
            err, sd = c["error"][key], c["std"][key]  # type: ignore[index]
            if not (math.isfinite(sd) and sd > 0):
                unstated += 1
                continue
            z.append(err / sd)
        za = np.abs(np.asarray(z))
        n = len(cases)
        out[key] = {
            "rms": float(np.sqrt(np.mean(za**2))) if za.size else math.nan,
            "within1": float(np.count_nonzero(za <= 1.0) / n) if n else math.nan,
            "within2": float(np.count_nonzero(za <= 2.0) / n) if n else math.nan,
            "n": float(n),
            "unstated": float(unstated),
        }
    return out
