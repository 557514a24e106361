"""Step 3: where the base model and the data disagree.

Residual ``r = v_measured - v_simulated`` examined

* against velocity, position and acceleration (binned means; the correlation
  ratio eta^2 says how much of the residual variance each explains) and
  direction of motion;
* in time: the share of residual energy right after reversals;
* in frequency: residual spectrum, residual-input cross-correlation and the
  whiteness of the residual (autocorrelation against its 95% band);
* across amplitude: the best linear approximation (first-order ARX) of each
  run, measured and simulated. A pole that moves more than the model predicts
  means friction-like feedback; gain rising with amplitude beyond the model
  means a dead zone, falling means saturation.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.identify.derivative import lowpass

#: Bins of the residual-versus-signal curves.
BINS = 24
#: Window after a velocity reversal counted as "just after" [s].
REVERSAL_WINDOW_S = 0.05
#: Largest lag of the correlation analyses [samples].
MAX_LAG = 50


def _change(after: float, before: float) -> float:
    """``after / before - 1``; NaN where ``before`` is 0 or either is not finite."""
    if not (before != 0 and math.isfinite(before) and math.isfinite(after)):
        return math.nan
    return after / before - 1


def _pct(change: float) -> str:
    """A relative change as signed whole per cent, ``undetermined`` where it is NaN."""
    return f"{100 * change:+.0f}%" if math.isfinite(change) else "undetermined"


@dataclass(frozen=True)
class Binned:
    """Mean residual per bin of a signal; ``eta2``: share of residual variance it explains."""

    centres: np.ndarray
    means: np.ndarray
    eta2: float


@dataclass(frozen=True)
class LinearApprox:
    """First-order best linear approximation of one run: pole [1/s] and DC gain."""

    run: int
    pole_measured: float
    gain_measured: float
    pole_simulated: float
    gain_simulated: float


@dataclass(frozen=True)
class Signatures:
    """Everything step 3 found; see the module docstring."""

    vs_velocity: Binned
    vs_position: Binned
    vs_acceleration: Binned
    mean_pos_direction: float
    mean_neg_direction: float
    reversal_energy_share: float
    reversal_time_share: float
    spectrum_hz: np.ndarray
    spectrum: np.ndarray
    peak_hz: float
    xcorr_peak: float
    xcorr_lag: int
    acf_max: float
    band95: float
    linear: tuple[LinearApprox, ...]

    def gain_change(self) -> tuple[float, float]:
        """Relative DC-gain change from the first to the last run: measured, simulated (NaN
        where the first run's gain is 0: a model at rest)."""
        a, b = self.linear[0], self.linear[-1]
        return _change(b.gain_measured, a.gain_measured), _change(b.gain_simulated, a.gain_simulated)

    def support(self, effect: str) -> str:
        """The step-3 finding that goes with ``effect``'s signature, as a clause ("" if none)."""
        if effect in ("stribeck", "viscous_asymmetry", "offset"):
            return f"velocity explains {100 * self.vs_velocity.eta2:.0f}% of the base residual"
        if effect == "cogging":
            return f"position explains {100 * self.vs_position.eta2:.0f}% of the base residual"
        if effect == "time_delay":
            return (
                f"residual-input cross-correlation {self.xcorr_peak:+.2f} at lag {self.xcorr_lag}"
            )
        if effect == "resonance":
            return f"the base residual spectrum peaks at {self.peak_hz:.3g} Hz"
        if effect == "backlash":
            return (
                f"{100 * self.reversal_energy_share:.0f}% of the residual energy in the "
                f"{100 * self.reversal_time_share:.0f}% of time after reversals"
            )
        if effect in ("deadzone", "saturation") and len(self.linear) >= 2:
            meas, sim = self.gain_change()
            return (
                f"the linear approximation's gain changes {_pct(meas)} from run "
                f"{self.linear[0].run} to run {self.linear[-1].run} (base model {_pct(sim)})"
            )
        return ""

    def findings(self) -> list[str]:
        """Plain sentences, strongest first."""
        out = []
        for label, b in (
            ("velocity", self.vs_velocity),
            ("position", self.vs_position),
            ("acceleration", self.vs_acceleration),
        ):
            out.append((b.eta2, f"{label} explains {100 * b.eta2:.0f}% of the residual variance"))
        if self.reversal_time_share > 0:
            ratio = self.reversal_energy_share / self.reversal_time_share
            out.append(
                (
                    min(ratio / 10, 1.0),
                    f"{100 * self.reversal_energy_share:.0f}% of the residual "
                    f"energy falls in the {100 * self.reversal_time_share:.0f}% of time just after reversals",
                )
            )
        out.append(
            (
                abs(self.xcorr_peak),
                f"residual-input cross-correlation peaks at "
                f"{self.xcorr_peak:+.2f} (lag {self.xcorr_lag}, 95% band +/-{self.band95:.2f})",
            )
        )
        white = "white" if self.acf_max <= self.band95 else "not white"
        out.append(
            (self.acf_max, f"the residual is {white} (largest autocorrelation {self.acf_max:.2f})")
        )
        out.append((0.0, f"the residual spectrum peaks at {self.peak_hz:.3g} Hz"))
        if len(self.linear) >= 2:
            a, b = self.linear[0], self.linear[-1]
            dg_meas, dg_sim = self.gain_change()
            dp_meas = _change(b.pole_measured, a.pole_measured)
            dp_sim = _change(b.pole_simulated, a.pole_simulated)
            text = (
                f"from run {a.run} to run {b.run} the linear approximation's gain changes "
                f"{_pct(dg_meas)} (model {_pct(dg_sim)}) and its pole {_pct(dp_meas)} "
                f"(model {_pct(dp_sim)})"
            )
            excess = dg_meas - dg_sim
            if excess > 0.05:
                text += ": gain rising with amplitude beyond the model suggests a dead zone"
            elif excess < -0.05:
                text += ": gain falling with amplitude suggests saturation"
            elif abs(dp_meas - dp_sim) > 0.05:
                text += ": a pole moving with amplitude suggests friction-like feedback"
            out.append((abs(excess) + abs(dp_meas - dp_sim), text))
        return [s for _, s in sorted(out, key=lambda item: -item[0])]


def _binned(signal: np.ndarray, residual: np.ndarray) -> Binned:
    edges = np.unique(np.quantile(signal, np.linspace(0, 1, BINS + 1)))
    if edges.size < 3:
        return Binned(np.array([float(np.mean(signal))]), np.array([float(np.mean(residual))]), 0.0)
    idx = np.clip(np.searchsorted(edges, signal, side="right") - 1, 0, edges.size - 2)
    counts = np.bincount(idx, minlength=edges.size - 1)
    sums = np.bincount(idx, weights=residual, minlength=edges.size - 1)
    ok = counts > 0
    means = np.where(ok, sums / np.maximum(counts, 1), np.nan)
    centres = 0.5 * (edges[:-1] + edges[1:])
    total = float(np.var(residual))
    between = float(np.sum(counts[ok] * (means[ok] - residual.mean()) ** 2) / residual.size)
    return Binned(centres[ok], means[ok], between / total if total > 0 else 0.0)


def _arx1(v: np.ndarray, u: np.ndarray, dt: float) -> tuple[float, float]:
    """Pole [1/s] and DC gain of ``v[k+1] = a v[k] + b u[k] + c``."""
    A = np.column_stack([v[:-1], u[:-1], np.ones(v.size - 1)])
    (a, b, _), *_ = np.linalg.lstsq(A, v[1:], rcond=None)
    a = min(max(a, 1e-9), 1 - 1e-9)
    return math.log(a) / dt, b / (1 - a)


def _norm_xcorr(a: np.ndarray, b: np.ndarray, max_lag: int) -> tuple[np.ndarray, np.ndarray]:
    a = (a - a.mean()) / (a.std() or 1.0)
    b = (b - b.mean()) / (b.std() or 1.0)
    n = a.size
    lags = np.arange(-max_lag, max_lag + 1)
    out = np.array(
        [np.dot(a[max(0, k) : n + min(0, k)], b[max(0, -k) : n - max(0, k)]) / n for k in lags]
    )
    return lags, out


def compute_signatures(data: DiagnosisData, v_sim: Sequence[np.ndarray]) -> Signatures:
    """Analyse the residual of the simulated velocity ``v_sim`` (one array per run)."""
    from servobench.bench.dsp.spectral import welch

    res, vel, pos, acc, rev = [], [], [], [], []
    linear = []
    for r, vs in zip(data.segments, v_sim, strict=True):
        ok = np.isfinite(vs)
        e = np.where(ok, r.v - vs, 0.0)
        res.append(e)
        vel.append(r.v_f)
        pos.append(r.position)
        acc.append(np.gradient(r.v_f, data.dt_s))
        flips = np.flatnonzero(np.diff(np.sign(r.v_f)) != 0)
        near = np.zeros(len(r.v), dtype=bool)
        span = max(1, int(REVERSAL_WINDOW_S * data.fs_hz))
        for i in flips:
            near[i : i + span] = True
        rev.append(near)
        vs_filled = lowpass(np.where(ok, vs, r.v), data.fs_hz)  # filtered like v_f
        pm, gm = _arx1(r.v_f, r.u, data.dt_s)
        ps, gs = _arx1(vs_filled, r.u, data.dt_s)
        linear.append(LinearApprox(r.run, pm, gm, ps, gs))
    e, v, x, a, near = (np.concatenate(z) for z in (res, vel, pos, acc, rev))
    u = data.cat("u")
    energy = float(np.sum(e * e)) or 1.0
    nper = int(min(max(64, 2 ** int(math.log2(max(e.size // 8, 64)))), e.size))
    freqs, psd = welch(e, data.fs_hz, nper)
    peak_hz = float(freqs[1 + int(np.argmax(psd[1:]))]) if psd.size > 1 else 0.0
    lags, xc = _norm_xcorr(e, u, MAX_LAG)
    i = int(np.argmax(np.abs(xc)))
    _, ac = _norm_xcorr(e, e, 20)
    acf = ac[21:]  # lags 1..20
    return Signatures(
        vs_velocity=_binned(v, e),
        vs_position=_binned(x, e),
        vs_acceleration=_binned(a, e),
        mean_pos_direction=float(e[v > 0].mean()) if np.any(v > 0) else 0.0,
        mean_neg_direction=float(e[v < 0].mean()) if np.any(v < 0) else 0.0,
        reversal_energy_share=float(np.sum(e[near] ** 2) / energy),
        reversal_time_share=float(near.mean()),
        spectrum_hz=freqs,
        spectrum=psd,
        peak_hz=peak_hz,
        xcorr_peak=float(xc[i]),
        xcorr_lag=int(lags[i]),
        acf_max=float(np.max(np.abs(acf))),
        band95=1.96 / math.sqrt(e.size),
        linear=tuple(linear),
    )
