"""What the identification plots show, computed from a result (pure: no I/O, no plotting).

* :func:`friction_map`: the friction force ``u - M dv/dt - B v`` binned by
  velocity, mean and spread per bin. Velocity and command pass through the
  project's zero-phase low-pass (:mod:`servobench.bench.identify.derivative`)
  before the acceleration is differentiated, so the filter cancels from the
  linear part and sensor noise does not swamp the friction: with
  ``noise = 0.01`` the raw sampled force spreads +-6 around a friction of
  0.5, the filtered one by a few hundredths.
* :func:`frf_evidence`: the spread of the differential FRF over the periods
  of a SIDBE log (the runs are periodic: every steady period is one
  estimate), and what the identified model *with its friction* gives
  through the same differential FRF. The differential pair
  ``(V1 - V2)/(U1 - U2)`` cancels friction only where both runs stick and
  slip together; at amplitudes near the friction level they do not, and the
  measured points sit off the linear block by an amount the simulated model
  reproduces.

Units: velocity [v unit], force [u unit], as the result's ``units`` state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.bench.identify.derivative import (
    default_cutoff_hz,
    filter_command,
    lowpass,
    settle_samples,
)
from servobench.bench.identify.frequency import line_spectrum
from servobench.bench.model.servo import IdentificationResult

#: Velocity bins on each side of zero in the friction map.
BINS_PER_DIRECTION = 12
#: Fewest samples a bin needs to be drawn.
MIN_BIN_SAMPLES = 20
#: Most raw samples kept for the faint background cloud.
MAX_CLOUD = 6000
#: Friction bias of the differential FRF worth a note [fraction of |G|].
BIAS_NOTE_FRACTION = 0.03
#: Relative agreement needed to accept the period length found for the stored FRF.
_REPRODUCE_RTOL = 1e-6


@dataclass(frozen=True)
class FrictionMap:
    """Friction force against velocity, binned.

    Attributes
    ----------
    v_centre : ndarray, shape (m,)
        Mean filtered velocity in each bin [v unit].
    force_mean, force_std : ndarray, shape (m,)
        Mean and standard deviation (the spread) of the friction force in the bin [u unit].
    count : ndarray of int, shape (m,)
        Samples in the bin.
    v_cloud, force_cloud : ndarray, shape (k,)
        An even thinning of all samples, for a faint background.
    cutoff_hz : float
        Cut-off of the zero-phase filter [Hz].
    coulomb_pos, coulomb_neg : float
        Identified Coulomb levels (magnitudes) [u unit].
    """

    v_centre: np.ndarray
    force_mean: np.ndarray
    force_std: np.ndarray
    count: np.ndarray
    v_cloud: np.ndarray
    force_cloud: np.ndarray
    cutoff_hz: float
    coulomb_pos: float
    coulomb_neg: float

    def __post_init__(self) -> None:
        m = self.v_centre.shape
        if not (self.force_mean.shape == self.force_std.shape == self.count.shape == m):
            raise ValueError("FrictionMap bin arrays must share one shape")

    def level_at(self, v: np.ndarray) -> np.ndarray:
        """The identified Coulomb force at velocities ``v``: +coulomb_pos, -coulomb_neg, 0 at rest."""
        v = np.asarray(v, dtype=float)
        return np.where(v > 0, self.coulomb_pos, np.where(v < 0, -self.coulomb_neg, 0.0))


def _run_force(t: np.ndarray, u: np.ndarray, v: np.ndarray, M: float, B: float):
    """Filtered velocity and ``u - M dv/dt - B v`` of one run, filter edges cut; or None."""
    if len(t) < 3:
        return None
    dt = float(np.median(np.diff(t)))
    fs = 1.0 / dt
    cutoff = default_cutoff_hz(fs)
    edge = settle_samples(fs, cutoff)
    if len(t) <= 2 * edge + MIN_BIN_SAMPLES:
        return None
    vf = lowpass(v, fs, cutoff)
    force = filter_command(u, fs, cutoff) - M * np.gradient(vf, dt) - B * vf
    keep = slice(edge, len(t) - edge)
    return vf[keep], force[keep], cutoff


def _bins(v: np.ndarray, force: np.ndarray, bins: int):
    """Per-direction equal-width bins up to the 99.5th percentile of |v|."""
    vmax = float(np.percentile(np.abs(v), 99.5))
    if not vmax > 0:
        return [np.empty(0)] * 3 + [np.empty(0, dtype=int)]
    inner = np.linspace(0.0, vmax, bins + 1)
    edges = np.concatenate((-inner[::-1], inner[1:]))
    index = np.digitize(v, edges) - 1
    centre, mean, std, count = [], [], [], []
    for i in range(len(edges) - 1):
        sel = index == i
        n = int(np.count_nonzero(sel))
        if n < MIN_BIN_SAMPLES:
            continue
        centre.append(float(v[sel].mean()))
        mean.append(float(force[sel].mean()))
        std.append(float(force[sel].std(ddof=1)))
        count.append(n)
    return np.array(centre), np.array(mean), np.array(std), np.array(count, dtype=int)


def friction_map(result: IdentificationResult, bins: int = BINS_PER_DIRECTION) -> FrictionMap | None:
    """The binned friction map of ``result``'s verification runs; None without them.

    Each run: velocity ``v`` and command ``u`` (as the held command the
    samples see) through the same zero-phase low-pass (cut-off ``fs/20``),
    acceleration by central differences of the filtered velocity, friction
    force ``u_f - M a - B v_f``; the filter's edge transients are cut.
    """
    ver = result.verification
    if ver is None:
        return None
    m = result.model
    vs, fs, cutoff = [], [], math.nan
    for run in ver.runs:
        got = _run_force(run.t, run.u, run.v, m.M, m.B)
        if got is not None:
            vs.append(got[0])
            fs.append(got[1])
            cutoff = got[2]
    if not vs:
        return None
    v, force = np.concatenate(vs), np.concatenate(fs)
    centre, mean, std, count = _bins(v, force, bins)
    step = max(1, v.size // MAX_CLOUD)
    return FrictionMap(centre, mean, std, count, v[::step], force[::step], cutoff,
                       m.coulomb_pos, m.coulomb_neg)  # fmt: skip


@dataclass(frozen=True)
class FrfEvidence:
    """The measured differential FRF with its spread and the model seen through it.

    Arrays of shape ``(m,)``, one entry per excited line.

    Attributes
    ----------
    f_hz : ndarray
        Line frequencies [Hz].
    measured : ndarray (complex)
        ``(V1 - V2)/(U1 - U2)``, mean over the steady periods [v unit per u unit].
    std_error : ndarray or None
        Standard error of ``measured`` from its spread over the periods
        (``|.|`` of the complex deviation) [v unit per u unit]; None when the
        periods cannot be told apart or fewer than two are steady.
    linear : ndarray (complex)
        The identified linear block, sampled exactly (ZOH) at the lines.
    with_friction : ndarray (complex) or None
        The same differential FRF of the model *simulated with its Coulomb
        friction* on the logged commands: what the measurement shows if the
        model is right, friction bias included.
    periods : int
        Steady periods averaged.
    amplitude : float
        Largest ``|u1|`` [u unit], of the excitation ``u_exc`` in closed loop; NaN
        without the logged runs.
    """

    f_hz: np.ndarray
    measured: np.ndarray
    std_error: np.ndarray | None
    linear: np.ndarray
    with_friction: np.ndarray | None
    periods: int
    amplitude: float

    @property
    def friction_bias(self) -> np.ndarray | None:
        """``|with_friction - linear| / |linear|`` per line: the friction bias the model predicts."""
        if self.with_friction is None:
            return None
        return np.abs(self.with_friction - self.linear) / np.abs(self.linear)

    @property
    def biased(self) -> bool:
        """True when the predicted friction bias reaches :data:`BIAS_NOTE_FRACTION` at some line."""
        bias = self.friction_bias
        return bias is not None and bool(np.max(bias) >= BIAS_NOTE_FRACTION)


def _period_samples(f_hz: np.ndarray, dt_s: float, periods: int, n_samples: int) -> list[int]:
    """Period lengths [samples] that put every line on a DFT bin, with ``periods`` of them in the run."""
    from fractions import Fraction
    from math import lcm

    n0 = 1
    for cycles_per_sample in f_hz * dt_s:
        n0 = lcm(n0, Fraction(float(cycles_per_sample)).limit_denominator(10**7).denominator)
    return [k * n0 for k in range(1, n_samples // (periods * n0) + 1)]


def _period_spectra(y: np.ndarray, n: int, lines: np.ndarray) -> np.ndarray:
    """Line spectra of the steady periods ``1 ..`` of ``y``, shape ``(periods, m)``."""
    whole = len(y) // n
    block = np.asarray(y[n : whole * n], dtype=float).reshape(whole - 1, n)
    return np.stack([line_spectrum(p, lines) for p in block])


def frf_evidence(result: IdentificationResult) -> FrfEvidence | None:
    """Spread and friction bias of ``result.frf``; None when the result has no FRF.

    The period length is the one for which every line is a DFT bin and the
    stored FRF is reproduced from the first periods of the logged runs (the
    transient one, then the averaged ones; ``auto`` holds the last period
    out). The spread is that of one steady period over all of them in the
    runs, divided by the root of the periods averaged; the spread and the
    model's differential FRF are None where no period length qualifies (an
    FRF measured on position, for one).
    """
    frf = result.frf
    if frf is None:
        return None
    linear = result.model.frequency_response(frf.f_hz, frf.dt_s)
    runs = {r.run: r for r in result.verification.runs} if result.verification else {}
    amplitude = _amplitude(runs[1]) if 1 in runs else math.nan
    found = _steady_periods(frf, runs)
    if found is None:
        return FrfEvidence(frf.f_hz, frf.G, None, linear, None, frf.periods_averaged, amplitude)
    n, lines = found
    r1, r2 = runs[1], runs[2]
    whole = min(len(r1.u), len(r2.u)) // n

    def spectra(y1: np.ndarray, y2: np.ndarray) -> np.ndarray:
        """Differential line spectra of every steady period in the runs, shape (periods, m)."""
        return _period_spectra(y1[: whole * n], n, lines) - _period_spectra(y2[: whole * n], n, lines)

    du = spectra(r1.u, r2.u).mean(axis=0)  # the command repeats exactly each period
    per_period = spectra(r1.v, r2.v) / du
    std_error = None
    if per_period.shape[0] >= 2:
        # spread of one period over all steady ones, then the standard error of the averaged FRF
        deviation = np.abs(per_period - per_period.mean(axis=0)) ** 2
        sigma = np.sqrt(deviation.sum(axis=0) / (per_period.shape[0] - 1))
        std_error = sigma / math.sqrt(frf.periods_averaged)
    averaged = slice(0, frf.periods_averaged)  # the periods the stored FRF averages
    sim = spectra(r1.v_sim, r2.v_sim)[averaged].mean(axis=0) / du
    return FrfEvidence(frf.f_hz, frf.G, std_error, linear, sim, frf.periods_averaged, amplitude)


def _amplitude(run) -> float:
    """The excitation's amplitude in run 1: its command, or in closed loop its excitation
    (the total command also holds the hold loop's share)."""
    return float(np.max(np.abs(run.u if run.u_exc is None else run.u_exc)))


def _steady_periods(frf, runs) -> tuple[int, np.ndarray] | None:
    """``(samples per period, DFT lines)`` that reproduce ``frf`` from runs 1 and 2, or None."""
    if 1 not in runs or 2 not in runs:
        return None
    r1, r2 = runs[1], runs[2]
    length = min(len(r1.u), len(r2.u))
    periods = frf.periods_averaged + 1  # the transient period, then the averaged ones
    for n in _period_samples(frf.f_hz, frf.dt_s, periods, length):
        lines = np.round(frf.f_hz * n * frf.dt_s).astype(int)
        spectra = [_period_spectra(y[: periods * n], n, lines).mean(axis=0) for y in (r1.u, r1.v, r2.u, r2.v)]
        g = (spectra[1] - spectra[3]) / (spectra[0] - spectra[2])
        if np.allclose(g, frf.G, rtol=_REPRODUCE_RTOL, atol=_REPRODUCE_RTOL * np.max(np.abs(frf.G))):
            return n, lines
    return None
