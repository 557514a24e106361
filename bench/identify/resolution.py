"""The step a drive reports a signal in: its resolution, and the noise that resolution is.

Many drives report velocity in whole units of their own -- 1 rpm on a CiA 402
drive whose 0x606C is in rpm, one encoder increment per cycle on others -- and
position in whole encoder increments. Such a signal takes few distinct values,
all on a grid of one step; its rounding error is up to half a step at every
sample (a whole step when the drive truncates) and, over a signal sweeping many
steps, uniform with standard deviation ``step / sqrt(12)``. Median-based noise
estimates see none of it (most second differences of a stepped signal are 0),
so the identification and diagnosis add it where they weigh noise.

A position from an encoder moves over many steps, so nearly every sample is
distinct and :func:`signal_step` sees no step; its step shows instead in the
differences between samples, all whole multiples of it (:func:`grid_step`).
"""

from __future__ import annotations

import math

import numpy as np

#: A signal is taken as reported in steps when at most this share of its samples are distinct.
STEPPED_SHARE = 0.5
#: :func:`grid_step`: the share of the differences that must be whole multiples of the step,
#: within this fraction of it, and the fewest steps the signal must span.
ON_GRID_SHARE = 0.99
ON_GRID_TOLERANCE = 0.01
MIN_GRID_STEPS = 50


def signal_step(y: np.ndarray) -> float:
    """The step ``y`` is reported in, 0 when it shows none [units of ``y``].

    The smallest difference between the distinct values of a signal with few of
    them (at most :data:`STEPPED_SHARE` of its samples); 0 for a signal with
    (almost) every sample distinct, as floating-point feedback with noise.

    >>> signal_step(np.array([0.0, 0.1, 0.1, 0.2, 0.1, 0.0]))
    0.1
    """
    y = np.asarray(y, dtype=float)
    levels = np.unique(y[np.isfinite(y)])
    if levels.size < 2 or levels.size > STEPPED_SHARE * y.size:
        return 0.0
    return float(np.round(np.diff(levels).min(), 15))


def grid_step(y: np.ndarray) -> float:
    """The step of the grid ``y``'s values lie on, from its differences; 0 when it shows none
    [units of ``y``].

    The smallest nonzero difference between consecutive samples, when at least
    :data:`ON_GRID_SHARE` of the differences are whole multiples of it (within
    :data:`ON_GRID_TOLERANCE` of a step) and ``y`` spans at least
    :data:`MIN_GRID_STEPS` steps: an encoder's position, a command logged in
    whole units. A signal of a few levels (a binary command) spans too few steps;
    floating-point feedback has differences on no common grid.

    >>> grid_step(0.05 * np.round(np.linspace(0.0, 10.0, 400) ** 1.5 / 0.05 * 0.1))
    0.05
    """
    y = np.asarray(y, dtype=float)
    d = np.abs(np.diff(y[np.isfinite(y)]))
    moves = d[d > 0]
    if moves.size < 2:
        return 0.0
    step = float(moves.min())
    if float(np.ptp(y[np.isfinite(y)])) < MIN_GRID_STEPS * step:
        return 0.0
    ratio = moves / step
    on = np.abs(ratio - np.round(ratio)) <= ON_GRID_TOLERANCE
    if on.mean() < ON_GRID_SHARE:
        return 0.0
    return float(f"{step:.9g}")  # differences of large values carry rounding


def step_noise_std(step: float) -> float:
    """Standard deviation [units of the signal] of rounding to ``step``: ``step / sqrt(12)``."""
    return step / math.sqrt(12.0)
