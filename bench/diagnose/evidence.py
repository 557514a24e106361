"""When a candidate pays: a held-out gain large enough, and larger than the noise can produce.

A candidate model pays against a reference when

* its held-out gap is at least :data:`MIN_GAIN` (relative) below the reference's, and
* the gain is not noise. On held-out samples the candidate's simulated velocity
  differs from the reference's by ``delta``; noise ``n`` on the measurement
  changes the drop of the mean squared error by ``2 mean(n delta)``, whose
  standard deviation is ``2 sigma rms(delta) / sqrt(N_eff)``. ``sigma`` is the
  rms of the candidate's own held-out residual (noise and whatever it leaves,
  so never below the noise) and ``N_eff`` the held-out samples divided by the
  residual's correlation length (coloured noise counts for fewer samples).
  The drop must stand :data:`MIN_Z` such standard deviations above zero. A
  flexible term that fits the noise of the training samples moves the
  simulation by little and at random on held-out ones, and gains nothing
  systematic there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData
from servobench.bench.diagnose.refit import FitResult

#: Relative held-out improvement a term (or a pair over a single) must bring.
MIN_GAIN = 0.15
#: Noise standard deviations the held-out drop of the squared error must stand above zero.
MIN_Z = 3.0
#: Longest lag [samples] of the residual's correlation length, and where its sum stops.
MAX_LAG = 400
ACF_STOP = 0.05


@dataclass(frozen=True)
class Payoff:
    """How a candidate compares with a reference on held-out samples.

    Attributes
    ----------
    reference_gap, gap : float
        Held-out gaps [%] of the reference and of the candidate.
    gain : float
        ``1 - gap / reference_gap``.
    z : float
        Drop of the held-out mean squared error over what the noise can produce (its std).
    samples : float
        Effective number of independent held-out samples ``N_eff``.
    """

    reference_gap: float
    gap: float
    gain: float
    z: float
    samples: float

    @property
    def pays(self) -> bool:
        return self.gain >= MIN_GAIN and self.z >= MIN_Z


def correlation_length(e: np.ndarray) -> float:
    """``1 + 2 sum(rho_k)`` over the lags before the autocorrelation first falls below
    :data:`ACF_STOP` (1 for white noise)."""
    e = e - e.mean()
    n = e.size
    if n < 4 or not np.any(e):
        return 1.0
    f = np.fft.rfft(e, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[: min(MAX_LAG, n - 1) + 1]
    rho = acf[1:] / acf[0]
    below = np.flatnonzero(rho < ACF_STOP)
    k = int(below[0]) if below.size else rho.size
    return max(1.0, 1.0 + 2.0 * float(np.sum(rho[:k])))


def payoff(data: DiagnosisData, reference: FitResult, candidate: FitResult) -> Payoff:
    """Compare ``candidate`` with ``reference`` on held-out samples (see the module docstring)."""
    delta, resid, drop = [], [], []
    for r, held, a, b in zip(
        data.segments, data.held_out, reference.v_sim, candidate.v_sim, strict=True
    ):
        ok = held & np.isfinite(a) & np.isfinite(b)
        delta.append(b[ok] - a[ok])
        resid.append(b[ok] - r.v[ok])
        drop.append((a[ok] - r.v[ok]) ** 2 - (b[ok] - r.v[ok]) ** 2)
    d, e, g = np.concatenate(delta), np.concatenate(resid), np.concatenate(drop)
    ref, gap = reference.gap_held_out, candidate.gap_held_out
    gain = 1.0 - gap / ref if ref > 0 else 0.0
    if e.size == 0:
        return Payoff(ref, gap, gain, 0.0, 0.0)
    samples = e.size / correlation_length(e)
    spread = 2.0 * float(np.sqrt(np.mean(e * e))) * float(np.sqrt(np.mean(d * d)))
    spread /= math.sqrt(samples)
    mean = float(np.mean(g))
    z = mean / spread if spread > 0 else (math.inf if mean > 0 else 0.0)
    return Payoff(ref, gap, gain, z, samples)
