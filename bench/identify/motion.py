"""Did the axis move above the sensor noise? Nothing can be identified from a log where it did not.

An estimator given a log of noise alone still returns numbers (SIDBE's
frequency response of noise gives ``M = 1.7e10``); the numbers mean nothing,
so the identification refuses such a log before any estimator runs.

The white sensor noise is estimated without a model, from the velocity's
second differences: for white noise ``e``, ``e[k] - 2 e[k-1] + e[k-2]`` has
variance ``6 sigma^2``, while a moving axis' velocity is smooth between
command switches (few samples), so the median absolute second difference,
scaled by ``1.4826 / sqrt(6)``, is ``sigma``. The axis moved when the
velocity's rms with the noise power taken out, ``sqrt(mean(v^2) - sigma^2)``,
reaches :data:`MIN_SIGNAL_TO_NOISE` times ``sigma`` in at least one run: a log
of noise alone gives about 0.1 (the variance estimate's own scatter), an axis
that moves at all gives well above 0.5.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from servobench.errors import IdentificationError

#: Least rms of the motion (noise power taken out) over the noise sigma, in one run at least.
MIN_SIGNAL_TO_NOISE = 0.5
#: Median absolute deviation to sigma of a normal distribution (1 / 0.6745).
_MAD_TO_SIGMA = 1.0 / 0.6745


@dataclass(frozen=True)
class Motion:
    """How far a log's velocity rises above its sensor noise.

    Attributes
    ----------
    noise_std : float
        White sensor noise of the velocity [velocity units/s] (0 for a noise-free log).
    signal_rms : float
        Largest rms over the runs of the velocity with the noise power taken out
        [velocity units/s].
    peak : float
        Largest |velocity| [velocity units/s].
    """

    noise_std: float
    signal_rms: float
    peak: float

    @property
    def moved(self) -> bool:
        if self.noise_std == 0.0:
            return self.peak > 0.0
        return self.signal_rms >= MIN_SIGNAL_TO_NOISE * self.noise_std


def second_difference_sigma(d2: np.ndarray) -> float:
    """White noise sigma behind second differences ``d2`` of a record, shape (m,) -> float.

    Robust (median absolute deviation): a smooth motion's few large second
    differences at command switches do not count. Diagnose's noise floor uses
    it too (:func:`servobench.bench.diagnose.data.noise_std`).
    """
    d2 = np.asarray(d2, dtype=float)
    if d2.size == 0:
        return 0.0
    return float(_MAD_TO_SIGMA * np.median(np.abs(d2 - np.median(d2))) / math.sqrt(6.0))


def sensor_noise_std(v: np.ndarray) -> float:
    """White noise sigma of a velocity record from its second differences, shape (n,) -> float."""
    v = np.asarray(v, dtype=float)
    return second_difference_sigma(np.diff(v, 2)) if v.size >= 3 else 0.0


def motion(velocities: list[np.ndarray], noise_std: float | None = None) -> Motion:
    """:class:`Motion` of the velocity records of a log's runs (each shape (n_i,)).

    ``noise_std``: the sensor noise sigma when the caller knows it better (diagnose
    adds the rounding of a velocity reported in steps, which second differences do
    not see); else each run's own from its second differences.
    """
    runs = [np.asarray(v, dtype=float) for v in velocities if v is not None and len(v)]
    if not runs:
        return Motion(0.0, 0.0, 0.0)
    sigmas = [sensor_noise_std(v) if noise_std is None else float(noise_std) for v in runs]
    weights = np.array([len(v) for v in runs], dtype=float)
    sigma = float(np.sqrt(np.average(np.square(sigmas), weights=weights)))
    signal = max(math.sqrt(max(0.0, float(np.mean(v**2)) - s**2)) for v, s in zip(runs, sigmas, strict=True))
    return Motion(sigma, signal, float(max(np.max(np.abs(v)) for v in runs)))


def require_motion(
    velocities: list[np.ndarray], where: str = "the log", noise_std: float | None = None
) -> Motion:
    """:func:`motion`, raising :class:`IdentificationError` when the axis did not move.

    The one motion rule of servobench: ``identify`` (and so ``sidbe``) and
    ``diagnose`` both refuse a log by it. The message says what to change: the
    amplitude (above the breakaway friction), and the drive's enable, brake and
    limits.
    """
    m = motion(velocities, noise_std)
    if not m.moved:
        raise IdentificationError(
            f"no motion above the sensor noise in {where}: the axis never moved (velocity rms {m.signal_rms:.3g} "
            f"beyond a noise sigma of {m.noise_std:.3g}, largest |v| {m.peak:.3g}): raise the amplitude "
            "above the breakaway friction, and check that the drive is enabled, the brake released "
            "and no limit holds the axis"
        )
    return m
