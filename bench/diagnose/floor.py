"""The noise floor of the velocity gap: what the data allow a perfect model to reach, part by part.

Every figure is a gap [% of the measured velocity's standard deviation], as the
gap itself. The *measurement floor* is the root sum of squares of independent
parts, each found from the log:

* measured velocity -- ``velocity noise``: white sensor noise from its second
  differences (:func:`~servobench.bench.diagnose.data.noise_std`), or from
  those of its residual against the final model where that is smaller (a fast
  plant's transients, a mode's ringing, move the velocity's own second
  differences for many samples after each switch);
  ``velocity step``: the rounding of a velocity the drive reports in whole
  steps, ``step / sqrt 12``. A reading in steps whose noise is not small
  against the step is not the two added: the noise dithers the rounding, and
  second differences of a reading on a grid (whole steps, a median of whole
  steps) see both. There the reading is matched by simulation
  (:func:`quantised_reading`): the final model's velocity plus white noise,
  rounded to the log's grid, the noise's level the one whose second
  differences move as often and as far as the log's; the parts are that noise
  and what the rounding adds to it, their root sum of squares the simulated
  reading's error;
* velocity derived from position -- ``position step``: the encoder's step,
  found from the differences of ``x``
  (:func:`~servobench.bench.identify.resolution.grid_step`), its rounding
  ``step / sqrt 12`` carried through the differentiating filter (its gain for
  white noise, from its frequency response); ``position noise``: the
  high-frequency part of the position (what the position filter removes),
  beyond what the step and the final model's own motion put there, through the
  same filter; ``velocity estimate``: the filter's smoothing of motion -- the
  final model's simulated velocity against the same estimate made from its own
  position, inside each comparison window away from its edges (a perfect
  model differs from a filtered derivative by this much);
* every log -- ``command step``: a command logged in whole steps, its rounding
  through the model's linear block ``1/(M s + B)``.

On top of it the held-out residual: of the final residual, the part no signal
of the log predicts on held-out samples (:mod:`.verdict`). Noise is independent
of the signals, so this bounds the noise from above; on a periodic excitation
so does the scatter of the velocity from period to period. When the residual
is noise-like (the signals predict less than ``STRUCTURED`` of it), the smaller
of the two raises the floor where it exceeds the measurement floor (coloured
noise); a residual the signals do predict keeps the measurement floor, so a
structure is not mistaken for noise. Where the final model holds the axis at
rest over much of a measured-velocity log, the residual there bounds the noise
from above too (:func:`rest_percent`): noise does not know whether the axis
moves, and at rest no timing of a slip can put a model error into it. A model
that places the slips of a sticking axis wrongly leaves a residual no signal
predicts, spikes at each slip; counted as coloured noise, it raised the floor
of such a log (a Stribeck curve four times the Coulomb level, read in steps)
to three times the true 10 %, where the residual at rest shows 14 %.
:attr:`NoiseFloor.source` says which, with every part and its value.

The floor's error bar is one-sided: the measurement floor is a lower bound
where the noise is coloured (second differences see low-passed noise only in
part), and the held-out residual's unpredictable part (or the period scatter,
or the residual at rest, the smallest) an upper one, tight where the log's
signals predict the structure. Where such a bound raised the floor, the bar
reaches down to the measurement floor (:attr:`NoiseFloor.lower_percent`): the
part of the residual no signal predicts may be structure the model misses
rather than noise. :attr:`NoiseFloor.upper_percent` is that bound
where it lies above the floor, widened by two of its own sampling errors
(:func:`rms_relative_se`: an rms read from a residual whose samples are
correlated rests on fewer independent ones): the noise can be up to there, and
a gap within it may be noise. Without the widening, ten of 112 coloured-noise
cases of ``diagnose_cases.py`` had their true floor 2-20 % above the bound. In
closed loop the loop's reaction cancels part of the noise in the measured
velocity from one period to the next: the period scatter bounds nothing there
(time delays in closed loop had their true floor 1.5-1.6 times it).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from servobench.bench.diagnose.data import DiagnosisData, noise_floor_percent
from servobench.bench.identify.derivative import differentiate_position, settle_samples
from servobench.bench.identify.motion import second_difference_sigma
from servobench.bench.identify.resolution import grid_step, step_noise_std

#: A residual whose places together predict less than this share is noise-like ...
STRUCTURED = 0.3
#: ... and its unpredictable part raises the floor when it exceeds the measurement floor this much.
COLOURED = 1.2
#: Time constants [s, samples] the linear block is held within (a fit with B near zero would
#: integrate the command's rounding into a drift).
TAU_MAX_S = 1.0
TAU_MIN_SAMPLES = 2
#: Normal consistency of the median absolute deviation.
MAD_NORMAL = 1.4826
#: A quantised reading's second differences are counted in whole steps up to this many times
#: their robust spread, and at least :data:`D2_CLIP_STEPS` steps (a switch of the command moves
#: the velocity further, in the log and in its simulation alike; noise does not).
D2_CLIP_SPREAD = 3.0
D2_CLIP_STEPS = 3
#: The residual at rest bounds the noise where the final model holds the axis at rest at this
#: share of the compared samples at least, and at :data:`REST_MIN_SAMPLES` samples at least.
REST_MIN_SHARE = 0.25
REST_MIN_SAMPLES = 500
#: The upper bound of the noise is widened by this many of its own sampling errors.
UPPER_SIGMAS = 2.0
#: :func:`rms_relative_se` sums the residual's squared autocorrelation out to this many times the
#: first lag at which it falls under :data:`DECORRELATED` (within a quarter of the samples).
CORRELATION_REACH = 2
DECORRELATED = 0.05
#: Bisections of the noise level a quantised reading is matched with (relative 2^-30).
MATCH_BISECTIONS = 30


@dataclass(frozen=True)
class FloorPart:
    """One independent part of the measurement floor: its name, its gap [%], how it was found."""

    name: str
    percent: float
    detail: str

    def as_dict(self) -> dict:
        return {"name": self.name, "percent": self.percent, "detail": self.detail}


@dataclass(frozen=True)
class NoiseFloor:
    """The noise floor [%] and its estimates; ``repeat_percent`` is None without periods.

    Attributes
    ----------
    percent : float
        The floor the verdict uses.
    sensor_percent : float
        The measurement floor: root sum of squares of ``parts``.
    repeat_percent : float or None
        Period-to-period scatter of the velocity.
    unpredictable_percent : float
        The final residual's part no signal predicts on held-out samples.
    rest_percent : float or None
        The final residual's rms where the final model holds the axis at rest
        (:func:`rest_percent`); None where it does not apply.
    bound_se : float
        The relative sampling error (1 sigma) of those bounds, each an rms of the log
        (:func:`rms_relative_se`).
    closed_loop : bool
        The log is a closed loop's: ``repeat_percent`` bounds nothing there (the loop's
        reaction cancels part of the noise in the measured velocity from one period to
        the next).
    rest_share : float
        The share of the samples ``rest_percent`` is read from (its sampling error is
        ``bound_se / sqrt(rest_share)``).
    lower_percent : float
        The least the noise can be: ``sensor_percent`` where a bound raised the floor, else
        ``percent``.
    upper_percent : float
        The most the noise can be: the smallest of ``unpredictable_percent``,
        ``repeat_percent`` and ``rest_percent`` times ``1 + UPPER_SIGMAS * bound_se``,
        and at least ``percent``.
    source : str
        Where ``percent`` comes from, with every part and its value, in words.
    parts : tuple of FloorPart
    """

    percent: float
    sensor_percent: float
    repeat_percent: float | None
    unpredictable_percent: float
    source: str
    parts: tuple[FloorPart, ...] = ()
    rest_percent: float | None = None
    bound_se: float = 0.0
    closed_loop: bool = False
    rest_share: float = 1.0

    @property
    def lower_percent(self) -> float:
        """The least the noise can be: the measurement floor where a bound raised the floor
        above it (that bound may hold structure no signal predicts), else the floor."""
        return min(self.percent, self.sensor_percent)

    @property
    def upper_percent(self) -> float:
        repeat = None if self.closed_loop else self.repeat_percent
        widened = [b * (1.0 + UPPER_SIGMAS * self.bound_se) for b in (self.unpredictable_percent, repeat)
                   if b is not None]  # fmt: skip
        if self.rest_percent is not None:
            widened.append(self.rest_percent * (1.0 + UPPER_SIGMAS * self.bound_se / math.sqrt(self.rest_share)))
        return max(self.percent, min(widened))


# ------------------------------------------------------------------ the filter's gains
def derivative_gain(fs_hz: float, cutoff_hz: float, method: str = "butter") -> float:
    """Standard deviation [1/s] of the derived velocity per unit of white position noise: the
    rms gain of the zero-phase filter and central difference over the band, from their
    frequency response (Savitzky-Golay: its derivative taps)."""
    dt = 1.0 / fs_hz
    if method == "savgol":
        from scipy.signal import savgol_coeffs

        window = max(5, int(round(fs_hz / cutoff_hz)) | 1)
        taps = savgol_coeffs(window, 3, deriv=1, delta=dt)
        return float(np.sqrt(np.sum(taps * taps)))
    from servobench.bench.dsp.iir import butter_lowpass, freqz

    b, a = butter_lowpass(4, cutoff_hz / (0.5 * fs_hz))
    w, h = freqz(b, a, points=8192)
    power = np.abs(h) ** 4 * (np.sin(w) / dt) ** 2  # forward-backward, then central difference
    return float(math.sqrt(np.trapezoid(power, w) / math.pi))


def block_gain(M: float, B: float, dt_s: float) -> float:
    """Standard deviation of velocity per unit of white force noise through ``1/(M s + B)``
    under zero-order hold (stationary); ``M/B`` held within [TAU_MIN_SAMPLES dt, TAU_MAX_S]."""
    B = min(max(B, M / TAU_MAX_S), M / (TAU_MIN_SAMPLES * dt_s))
    a = math.exp(-dt_s * B / M)
    b = (1.0 - a) / B
    return b / math.sqrt(1.0 - a * a)


# ------------------------------------------------------------------ parts
def _mad_sigma(y: np.ndarray) -> float:
    return MAD_NORMAL * float(np.median(np.abs(y - np.median(y))))


def _windows(data: DiagnosisData, i: int) -> list[tuple[int, int]]:
    starts = data.starts[i]
    ends = np.append(starts[1:], len(data.segments[i]))
    return [(int(s), int(e)) for s, e in zip(starts, ends, strict=True)]


def _model_positions(data: DiagnosisData, v_sim: Sequence[np.ndarray], edge: int):
    """Per comparison window: the model's simulated velocity and the position it integrates to
    from the measured position at the window's start (trapezoids). Windows shorter than
    ``edge`` samples at each end and some between, or that the simulation did not reach, are
    left out: the filter's edge transient (its padding) is not the estimate's smoothing."""
    for i, (r, vs) in enumerate(zip(data.segments, v_sim, strict=True)):
        if r.motion is None:
            continue
        for s, e in _windows(data, i):
            w = np.asarray(vs[s:e], dtype=float)
            if w.size < 2 * edge + 10 or not np.all(np.isfinite(w)):
                continue
            steps = 0.5 * (w[1:] + w[:-1]) * data.dt_s
            yield r, w, float(r.position[s]) + np.concatenate([[0.0], np.cumsum(steps)])


def _on_grid(x: np.ndarray, step: float, like: np.ndarray) -> np.ndarray:
    """``x`` rounded to the grid of ``step`` that ``like``'s values lie on."""
    if step <= 0:
        return x
    origin = float(like[0]) - step * round(float(like[0]) / step)
    return origin + step * np.round((x - origin) / step)


def derived_parts(data: DiagnosisData, v_sim: Sequence[np.ndarray]) -> list[FloorPart]:
    """Parts of a velocity derived from position (see the module docstring)."""
    segments = [s for s in data.segments if s.motion is not None and s.x is not None]
    if not segments:
        return []
    fs, spread = data.fs_hz, float(np.std(data.cat("v")))
    cutoff, method = segments[0].motion.cutoff_hz, segments[0].motion.method
    unit_x, unit_v = data.units.of("x"), data.units.of("v")
    gain = derivative_gain(fs, cutoff, method)
    step = grid_step(np.concatenate([s.x for s in segments]))
    share = max(1e-3, 1.0 - cutoff / (0.5 * fs))  # of white noise above the cut-off
    measured = _mad_sigma(np.concatenate([s.x - s.motion.x for s in segments])) / math.sqrt(share)
    # What the step and the model's own motion alone put in the high-frequency part.
    lag, own = [], []
    edge = settle_samples(fs, cutoff)
    for r, w, x in _model_positions(data, v_sim, edge):
        est = differentiate_position(x, fs, cutoff, method).v
        lag.append((est - w)[edge:-edge])
        xq = _on_grid(x, step, r.x)
        own.append((xq - differentiate_position(xq, fs, cutoff, method).x)[edge:-edge])
    expected = _mad_sigma(np.concatenate(own)) / math.sqrt(share) if own else 0.0
    noise_x = math.sqrt(max(0.0, measured**2 - expected**2))
    pct = 100.0 / spread if spread > 0 else 0.0
    parts = [
        FloorPart(
            "position noise",
            pct * noise_x * gain,
            f"the position's high-frequency part beyond its step and the model's own motion, "
            f"{noise_x:.3g} {unit_x} rms, through the differentiating filter ({gain:.4g} 1/s "
            f"for white noise, cut-off {cutoff:.4g} Hz)",
        )
    ]
    if step > 0:
        parts.append(
            FloorPart(
                "position step",
                pct * step_noise_std(step) * gain,
                f"the encoder's step of {step:.4g} {unit_x} in the differences of x (step / "
                f"sqrt 12 = {step_noise_std(step):.3g} {unit_x}) through the same filter",
            )
        )
    if lag:
        e = np.concatenate(lag)
        parts.append(
            FloorPart(
                "velocity estimate",
                pct * float(np.sqrt(np.mean(e * e))),
                f"the filter's smoothing of motion: the final model's velocity against the same "
                f"estimate from its own position, {float(np.sqrt(np.mean(e * e))):.3g} {unit_v} "
                "rms",
            )
        )
    return parts


def _d2_steps(readings: Sequence[np.ndarray], step: float, clip: float) -> float:
    """Mean size [steps] of the second differences of readings on a grid of ``step``, each
    counted up to ``clip`` steps."""
    d2 = np.concatenate([np.abs(np.round(np.diff(r, 2) / step)) for r in readings])
    return float(np.mean(np.minimum(d2, clip))) if d2.size else 0.0


def quantised_reading(
    readings: Sequence[np.ndarray], v_model: Sequence[np.ndarray], step: float, seed: int = 0
) -> tuple[float, float]:
    """The white noise behind velocity ``readings`` reported in steps of ``step`` [units/s], and
    the rms error of such a reading, both [units/s], per run arrays of equal lengths.

    The model's velocity ``v_model`` (noise-free) plus white noise of a level ``sigma``, rounded
    to the readings' grid, is a simulated reading; ``sigma`` is the level whose second
    differences are as large on average (:func:`_d2_steps`) as the readings' (bisection, the
    same noise draws at every level). The error is the simulated reading's against
    ``v_model``. With no noise (a reading that moves only where the motion crosses a step) the
    error is the rounding's, about ``step / sqrt 12``; with noise large against the step,
    ``sqrt(sigma^2 + step^2 / 12)``; between, the noise dithers the rounding, and neither
    second differences alone nor the two added are right.
    """
    pairs = []
    for r, vm in zip(readings, v_model, strict=True):
        ok = np.isfinite(vm) & np.isfinite(r)
        if ok.sum() > 2:
            pairs.append((np.asarray(r, dtype=float)[ok], np.asarray(vm, dtype=float)[ok]))
    if not pairs or step <= 0:
        return 0.0, 0.0
    rng = np.random.default_rng(seed)
    draws = [rng.standard_normal(vm.size) for _, vm in pairs]

    def simulated(sigma: float) -> list[np.ndarray]:
        return [_on_grid(vm + sigma * n, step, r) for (r, vm), n in zip(pairs, draws, strict=True)]

    d2 = np.concatenate([np.diff(r, 2) for r, _ in pairs]) / step
    clip = max(D2_CLIP_STEPS, math.ceil(D2_CLIP_SPREAD * _mad_sigma(d2)))

    def size(readings: list[np.ndarray]) -> float:
        return _d2_steps(readings, step, clip)

    target = size([r for r, _ in pairs])
    lo, hi = 0.0, step
    if size(simulated(lo)) >= target:
        hi = 0.0
    else:
        while size(simulated(hi)) < target and hi < 1e3 * step:
            lo, hi = hi, 2.0 * hi
        for _ in range(MATCH_BISECTIONS):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if size(simulated(mid)) < target else (lo, mid)
    sigma = 0.5 * (lo + hi)
    err = np.concatenate([q - vm for q, (_, vm) in zip(simulated(sigma), pairs, strict=True)])
    return sigma, float(np.sqrt(np.mean(err * err)))


def sensor_floor_percent(data: DiagnosisData, v_model: Sequence[np.ndarray]) -> float:
    """Gap [%] that the velocity sensor's noise alone leaves, the search's floor: white noise
    from second differences (:func:`~servobench.bench.diagnose.data.noise_floor_percent`), or
    from those of the residual against the model's velocity ``v_model`` per run where smaller
    (:func:`_residual_noise`); a velocity read in steps, the reading's error matched on
    ``v_model`` (:func:`quantised_reading`): the root sum of squares of :func:`measured_parts`.
    A velocity derived from position has no sensor noise of its own (0)."""
    if data.derived:
        return noise_floor_percent(data)
    return math.sqrt(sum(p.percent**2 for p in measured_parts(data, v_model)))


def _residual_noise(data: DiagnosisData, v_model: Sequence[np.ndarray]) -> float | None:
    """White noise [units/s] from the second differences of the measured velocity's residual
    against the model's ``v_model`` (where all three samples are simulated), robustly; None
    where too few. A fast plant's transients after each switch move the velocity's own second
    differences for many samples, too many for their median to leave out; the residual's
    carry only what the model misses."""
    d2 = []
    for r, vm in zip(data.segments, v_model, strict=True):
        e = np.asarray(r.v, dtype=float) - np.asarray(vm, dtype=float)
        d = np.diff(e, 2)
        d2.append(d[np.isfinite(d)])
    d2 = np.concatenate(d2) if d2 else np.empty(0)
    return second_difference_sigma(d2) if d2.size >= 100 else None


def measured_parts(data: DiagnosisData, v_sim: Sequence[np.ndarray]) -> list[FloorPart]:
    """Parts of a measured velocity: white noise and the rounding of a stepped velocity (a
    quantised reading matched by simulation on the final model's velocity ``v_sim``)."""
    spread = float(np.std(data.cat("v")))
    pct = 100.0 / spread if spread > 0 else 0.0
    rounding = step_noise_std(data.v_step)
    unit_v = data.units.of("v")
    if data.v_step > 0:
        sigma, error = quantised_reading([r.v for r in data.segments], v_sim, data.v_step)
        if error > 0:
            beyond = math.sqrt(max(0.0, error**2 - sigma**2))
            return [
                FloorPart(
                    "velocity noise",
                    pct * sigma,
                    f"white sensor noise under a reading in steps of {data.v_step:.4g} {unit_v}, "
                    f"{sigma:.3g} {unit_v} rms: the level at which the final model's velocity, "
                    "noisy and rounded, moves as the log's second differences do",
                ),
                FloorPart(
                    "velocity step",
                    pct * beyond,
                    f"the rounding of a velocity reported in steps of {data.v_step:.4g} {unit_v}: "
                    f"what it adds to that noise in the simulated reading, whose error is "
                    f"{error:.3g} {unit_v} rms (undithered, step / sqrt 12 = {rounding:.3g} "
                    f"{unit_v})",
                ),
            ]
    white = math.sqrt(max(0.0, data.sigma_v**2 - rounding**2))
    residual = _residual_noise(data, v_sim)
    of = "the measured velocity"
    if residual is not None and residual < white:
        white, of = residual, "the measured velocity's residual against the final model"
    parts = [
        FloorPart(
            "velocity noise",
            pct * white,
            f"white sensor noise from the second differences of {of}, {white:.3g} {unit_v} rms",
        )
    ]
    if data.v_step > 0:
        parts.append(
            FloorPart(
                "velocity step",
                pct * rounding,
                f"the rounding of a velocity reported in steps of {data.v_step:.4g} {unit_v} "
                f"(step / sqrt 12 = {rounding:.3g} {unit_v})",
            )
        )
    return parts


def command_part(data: DiagnosisData, base: Mapping[str, float]) -> FloorPart | None:
    """The rounding of a command logged in steps, through the model's linear block."""
    step = grid_step(data.cat("u"))
    spread = float(np.std(data.cat("v")))
    if step <= 0 or spread <= 0:
        return None
    sigma = step_noise_std(step) * block_gain(float(base["M"]), float(base["B"]), data.dt_s)
    unit_u = data.units.of("u")
    return FloorPart(
        "command step",
        100.0 * sigma / spread,
        f"a command logged in steps of {step:.4g} {unit_u} (step / sqrt 12 = "
        f"{step_noise_std(step):.3g} {unit_u}) through the model's linear block 1/(M s + B)",
    )


def repeat_percent(data: DiagnosisData) -> float | None:
    """Period-to-period scatter [%] of the velocity after the first period; None without three
    periods of a periodic design."""
    design = data.prepared.design
    periods = data.prepared.periodic_periods()
    if design is None or periods < 3:
        return None
    n = design.samples_per_period
    sq, count = 0.0, 0
    for r in data.segments:
        V = r.v[n : periods * n].reshape(periods - 1, n)
        dev = V - V.mean(axis=0)
        sq += float(np.sum(dev * dev))
        count += (periods - 2) * n
    spread = float(np.std(data.cat("v")))
    return 100.0 * math.sqrt(sq / count) / spread if spread > 0 and count else None


def rest_percent(data: DiagnosisData, v_sim: Sequence[np.ndarray]) -> tuple[float, float] | None:
    """The final residual's rms [%] over the samples where the model holds the axis at rest (its
    simulated velocity exactly zero), and their share of the samples: the noise plus whatever
    the model misses there, an upper bound of the noise. None for a velocity derived from
    position (its filter spreads motion into the rest next to it) and where the model rests at
    fewer than :data:`REST_MIN_SHARE` of the samples or :data:`REST_MIN_SAMPLES`."""
    if data.derived:
        return None
    sq, rest, total = 0.0, 0, 0
    for r, vs in zip(data.segments, v_sim, strict=True):
        vs = np.asarray(vs, dtype=float)
        still = vs == 0.0
        total += vs.size
        rest += int(np.count_nonzero(still))
        sq += float(np.sum(r.v[still] ** 2))
    spread = float(np.std(data.cat("v")))
    if spread <= 0 or rest < max(REST_MIN_SAMPLES, REST_MIN_SHARE * total):
        return None
    return 100.0 * math.sqrt(sq / rest) / spread, rest / total


def rms_relative_se(residuals: Sequence[np.ndarray]) -> float:
    """Relative standard error (1 sigma) of the rms of ``residuals`` (one array per run) as an
    estimate of their process's: ``1 / sqrt(2 N_eff)``, with ``N_eff = N / sum_k rho_k^2`` over
    every lag ``k`` (Bartlett's variance of a sample variance). The pooled autocorrelation
    ``rho`` is summed out to :data:`CORRELATION_REACH` times the lag at which it first falls
    under :data:`DECORRELATED`; white samples give ``1 / sqrt(2 N)``."""
    runs = [np.asarray(r, dtype=float) for r in residuals]
    runs = [r[np.isfinite(r)] for r in runs]
    runs = [r - r.mean() for r in runs if r.size > 8]
    n = sum(r.size for r in runs)
    if n == 0:
        return 0.0
    reach = max(1, min(r.size for r in runs) // 4)
    acf = np.zeros(reach + 1)
    for r in runs:
        size = 1 << int(2 * r.size - 1).bit_length()
        spectrum = np.fft.rfft(r, size)
        acf += np.fft.irfft(spectrum * np.conj(spectrum), size)[: reach + 1]
    if acf[0] <= 0:
        return 0.0
    rho = acf / acf[0]
    under = np.flatnonzero(np.abs(rho) < DECORRELATED)
    stop = min(reach, CORRELATION_REACH * int(under[0])) if under.size else reach
    n_eff = n / (1.0 + 2.0 * float(np.sum(rho[1 : stop + 1] ** 2)))
    return 1.0 / math.sqrt(2.0 * max(n_eff, 1.0))


def _listed(parts: Sequence[FloorPart]) -> str:
    return "; ".join(f"{p.name} {p.percent:.3g}% ({p.detail})" for p in parts)


def noise_floor(
    data: DiagnosisData,
    gap: float,
    together: float,
    v_sim: Sequence[np.ndarray],
    base: Mapping[str, float],
) -> NoiseFloor:
    """The noise floor of a final model (``base``, simulated velocity ``v_sim`` per run) with
    ``gap`` [%] whose residual the places predict ``together`` of on held-out samples; see the
    module docstring."""
    parts = derived_parts(data, v_sim) if data.derived else measured_parts(data, v_sim)
    command = command_part(data, base)
    parts += [command] if command is not None else []
    sensor = math.sqrt(sum(p.percent**2 for p in parts))
    repeat = repeat_percent(data)
    rest, rest_share = rest_percent(data, v_sim) or (None, 1.0)
    unpredictable = gap * math.sqrt(max(0.0, 1.0 - together))
    floor = sensor
    source = f"the measurement, {sensor:.3g}% (root sum of squares of: {_listed(parts)})"
    if together < STRUCTURED:
        bounds = {}  # the upper bounds of the noise, in words; the first of equal ones is said
        if repeat is not None:
            bounds[f"the scatter of the velocity from one excitation period to the next, {repeat:.3g}%"] = repeat
        bounds[f"the part of the residual no signal of the log predicts on held-out samples "
               f"(coloured noise), {unpredictable:.3g}%"] = unpredictable  # fmt: skip
        if rest is not None:
            bounds[f"the residual where the model holds the axis at rest, {rest:.3g}%"] = rest
        said, upper = min(bounds.items(), key=lambda item: item[1])
        if upper > COLOURED * sensor:
            floor = upper
            source = f"{said}, above the measurement's {sensor:.3g}% ({_listed(parts)})"
        elif upper == rest and min(unpredictable, math.inf if repeat is None else repeat) > COLOURED * sensor:
            source += (
                f"; the residual's part no signal predicts on held-out samples, {unpredictable:.3g}%, "
                f"is not counted: the residual where the model holds the axis at rest, {rest:.3g}%, "
                "does not exceed it, and noise does not know whether the axis moves"
            )
        else:
            source += (
                f"; the residual's part no signal predicts on held-out samples, "
                f"{unpredictable:.3g}%, does not exceed it"
            )
    else:
        source += (
            f"; the held-out residual's unpredictable part, {unpredictable:.3g}%, is not "
            f"counted: the log's signals predict {100 * together:.0f}% of the residual on "
            "held-out samples (a structure, not noise)"
        )
        if unpredictable > COLOURED * sensor:
            source += (
                "; it bounds the noise from above: coloured noise, which second differences "
                f"see only in part, can be up to {unpredictable:.3g}%"
            )
    se = rms_relative_se([r.v - vs for r, vs in zip(data.segments, v_sim, strict=True)])
    return NoiseFloor(floor, sensor, repeat, unpredictable, source, tuple(parts), rest, se,
                      data.prepared.closed_loop, rest_share)  # fmt: skip
