"""INTERIM stand-in for :func:`bench.procedure.run_sidbe` until it lands.

A binary random excitation in two runs (amplitude ``A`` and ``r A``), streamed
with :func:`bench.runner.stream_runs`, and a least-squares fit of the exact
ZOH step with Coulomb friction per direction::

    v_{k+1} = a v_k + c u_k - c fc_pos [moving +] + c fc_neg [moving -]

Only intervals where the velocity keeps its sign enter the fit. This module
is deleted once :mod:`bench.procedure` exists.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from bench.logio import read_log
from bench.runner import stream_runs
from drivers.base import Drive
from drivers.errors import IdentificationError


def _excitation(n: int, amplitude: float, dwell: int, rng: np.random.Generator) -> np.ndarray:
    levels = []
    sign = 1.0
    while len(levels) < n:
        levels.extend([sign * amplitude] * int(rng.integers(dwell, 4 * dwell)))
        sign = -sign
    return np.array(levels[:n])


def _fit(log, fs_hz: float) -> tuple[dict[str, float], dict[str, float]]:
    rows, target = [], []
    for run in log.runs:
        v0, v1, u = run.v[:-1], run.v[1:], run.u[:-1]
        pos = (v0 > 0) & (v1 > 0)
        neg = (v0 < 0) & (v1 < 0)
        keep = pos | neg
        rows.append(np.column_stack([v0, u, -pos.astype(float), neg.astype(float)])[keep])
        target.append(v1[keep])
    X = np.concatenate(rows).astype(float)
    y = np.concatenate(target)
    if X.shape[0] < 20 or not X[:, 2].any() or not X[:, 3].any():
        raise IdentificationError("too little motion in both directions to identify the model")
    theta, *_ = np.linalg.lstsq(X, y, rcond=None)
    a, c, dp, dn = theta
    if not (0 < a < 1 and c > 0):
        raise IdentificationError(f"the fit gave an unstable or inverted plant (a={a:.4g}, c={c:.4g})")
    resid = y - X @ theta
    cov = np.linalg.pinv(X.T @ X) * float(resid @ resid) / max(X.shape[0] - 4, 1)
    sa, sc, sdp, sdn = np.sqrt(np.abs(np.diag(cov)))
    T = 1.0 / fs_hz
    B = (1 - a) / c
    M = -B * T / math.log(a)
    params = {"M": M, "B": B, "coulomb_pos": dp / c, "coulomb_neg": dn / c}
    std = {
        "B": math.hypot(sa / c, B * sc / c),
        "M": M * math.hypot(sa / (a * abs(math.log(a))), math.hypot(sa / c, B * sc / c) / B),
        "coulomb_pos": math.hypot(sdp / c, dp * sc / c**2),
        "coulomb_neg": math.hypot(sdn / c, dn * sc / c**2),
    }
    return params, std


def run_sidbe(
    drive: Drive,
    options: Mapping[str, Any],
    out_dir: Path,
    progress: Callable[[int, int], None] | None = None,
):
    from bench.commission.integration import IdentifiedModel, SidbeOutcome
    from sim_backend.plant import PlantParams, simulate_coulomb

    fs = float(options.get("fs_hz", 1000.0))
    amplitude = float(options.get("amplitude", 0.5 * drive.limits.max_command))
    ratio = float(options.get("ratio", 0.9))
    n = int(float(options.get("duration_s", 3.0)) * fs)
    rng = np.random.default_rng(int(options.get("seed", 1)))
    u1 = _excitation(n, amplitude, max(1, int(0.02 * fs)), rng)
    log_path = out_dir / "log.csv"
    stream_runs(drive, [(1, u1), (2, ratio * u1)], fs, log_path, progress=progress,
                metadata={"procedure": "interim"})  # fmt: skip
    log = read_log(log_path)
    params, std = _fit(log, fs)
    plant = PlantParams(M=params["M"], B=params["B"], fc_pos=max(params["coulomb_pos"], 1e-12),
                        fc_neg=max(params["coulomb_neg"], 1e-12))  # fmt: skip
    run = log.runs[0]
    sim, _, _ = simulate_coulomb(run.u, 1.0 / fs, plant)
    fit = 100.0 * (1.0 - np.linalg.norm(run.v - sim) / np.linalg.norm(run.v - run.v.mean()))
    ident = {
        **params,
        "pole": -params["B"] / params["M"],
        "dc_gain": 1.0 / params["B"],
        "fit_percent": float(fit),
        "method": "interim-ls",
    }
    model = IdentifiedModel(**params, std=std, fit_percent=float(fit), method="interim-ls",
                            identify_json=ident)  # fmt: skip
    return SidbeOutcome(model=model, log_path=log_path, fs_hz=fs, details={"procedure": "interim"})
