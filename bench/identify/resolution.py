"""The step a drive reports a signal in: its resolution, and the noise that resolution is.

Many drives report velocity in whole units of their own -- 1 rpm on a CiA 402
drive whose 0x606C is in rpm, one encoder increment per cycle on others -- and
position in whole encoder increments. Such a signal takes few distinct values,
all on a grid of one step; its rounding error is up to half a step at every
sample (a whole step when the drive truncates) and, over a signal sweeping many
steps, uniform with standard deviation ``step / sqrt(12)``. Median-based noise
estimates see none of it (most second differences of a stepped signal are 0),
so the identification and diagnosis add it where they weigh noise.
"""

from __future__ import annotations

import math

import numpy as np

#: A signal is taken as reported in steps when at most this share of its samples are distinct.
STEPPED_SHARE = 0.5


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


def step_noise_std(step: float) -> float:
    """Standard deviation [units of the signal] of rounding to ``step``: ``step / sqrt(12)``."""
    return step / math.sqrt(12.0)
