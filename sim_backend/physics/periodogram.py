"""The sine/cosine periodogram of a signal sampled at irregular positions, compiled.

:func:`sincos_power` is the least-squares power of a sine and a cosine at each of evenly
spaced frequencies (a Lomb-Scargle periodogram without the phase shift), the cogging screen's
search for a force periodic in position (:mod:`~servobench.sim_backend.physics.effects.cogging`).
Pure: arrays in, an array out.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def sincos_power(ks: np.ndarray, x: np.ndarray, e: np.ndarray, block: int) -> np.ndarray:
    """The sin/cos power of ``e`` at each spatial frequency ``ks`` (evenly spaced) over ``x``:
    ``(sum e sin)^2 / sum sin^2 + (sum e cos)^2 / sum cos^2``.

    Compiled, one pass over the samples per frequency: each sample's ``exp(i k x)`` is carried
    from one frequency to the next by ``exp(i dk x)`` (one complex product instead of a sine and
    a cosine) and taken afresh every ``block`` frequencies, so rounding cannot build up (the
    powers agree with the direct sums within 2e-14 of the largest, as numpy's block products of
    exponentials before it did; 17 ms against 53 ms for 2000 frequencies over 6000 samples).
    ``sum sin^2`` and ``sum cos^2`` are ``(n -+ Re sum exp(2 i k x)) / 2``.
    """
    n, count = x.size, ks.size
    dk = ks[1] - ks[0] if count > 1 else 0.0
    zr, zi = np.empty(n), np.empty(n)
    sr, si = np.cos(dk * x), np.sin(dk * x)
    power = np.empty(count)
    for i in range(count):
        if i % block == 0:
            for j in range(n):
                zr[j], zi[j] = math.cos(ks[i] * x[j]), math.sin(ks[i] * x[j])
        se_r = se_i = z2 = 0.0
        for j in range(n):
            a, b = zr[j], zi[j]
            se_r += a * e[j]
            se_i += b * e[j]
            z2 += a * a - b * b
            zr[j], zi[j] = a * sr[j] - b * si[j], a * si[j] + b * sr[j]
        power[i] = se_i * se_i / (0.5 * (n - z2)) + se_r * se_r / (0.5 * (n + z2))
    return power
