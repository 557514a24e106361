"""The zero-phase low-pass the identification and the diagnosis filter with (thousands of times a
diagnosis) against ``scipy.signal.filtfilt``: the same numbers bit for bit, with the filter's
steady state solved once per filter instead of on every call."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from servobench.bench.identify.derivative import FILTER_ORDER, butterworth, lowpass
from servobench.errors import IdentificationError


def test_lowpass_is_scipys_filtfilt_bit_for_bit():
    rng = np.random.default_rng(0)
    for _ in range(100):
        n = int(rng.integers(16, 3000))
        fs = float(rng.choice([100.0, 500.0, 1000.0, 2000.0]))
        fc = fs * rng.uniform(0.01, 0.45)
        b, a = butterworth(FILTER_ORDER, fc / (fs / 2))
        for shape, axis in (((n,), 0), ((n, 3), 0), ((2, n), 1), ((2, n), -1)):
            y = rng.normal(size=shape).cumsum(axis=axis)
            got = lowpass(y, fs, fc, axis=axis)
            want = signal.filtfilt(b, a, y, axis=axis)
            assert got.shape == want.shape
            assert np.array_equal(got, want)


def test_lowpass_refuses_too_short_a_signal():
    with pytest.raises(IdentificationError, match="too few samples"):
        lowpass(np.zeros(15), 1000.0, 50.0)
