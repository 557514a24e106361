"""The signal processing the identification and the diagnosis call thousands of times
(:mod:`servobench.bench.dsp`) against scipy.signal, the implementation it was written from:
the Butterworth design, ``lfilter`` and its steady state bit for bit, Welch's densities and the
frequency response within rounding; and a process that filters and takes spectra this way
never imports scipy.signal (0.6 s a process)."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
from scipy import signal

from servobench.bench.dsp import iir, spectral


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6, 8])
def test_the_butterworth_design_is_scipys_bit_for_bit(order):
    rng = np.random.default_rng(order)
    for wn in rng.uniform(0.002, 0.995, 200):
        b, a = iir.butter_lowpass(order, float(wn))
        want_b, want_a = signal.butter(order, wn)
        assert b.dtype == want_b.dtype and a.dtype == want_a.dtype
        assert np.array_equal(b, want_b) and np.array_equal(a, want_a), wn
        assert np.array_equal(iir.lfilter_zi(b, a), signal.lfilter_zi(want_b, want_a))


def test_the_design_refuses_a_cut_off_outside_nyquist():
    for wn in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ValueError, match="cut-off"):
            iir.butter_lowpass(4, wn)


def test_lfilter_is_scipys_bit_for_bit():
    rng = np.random.default_rng(3)
    for _ in range(40):
        b, a = signal.butter(int(rng.integers(1, 7)), rng.uniform(0.01, 0.9))
        for shape, axis in (((700,), 0), ((500, 3), 0), ((2, 400), 1), ((2, 400), -1), ((3, 50, 2), 1)):
            x = rng.normal(size=shape).cumsum(axis=axis)
            assert np.array_equal(iir.lfilter(b, a, x, axis=axis), signal.lfilter(b, a, x, axis=axis))
            zshape = list(shape)
            zshape[axis] = len(a) - 1
            zi = rng.normal(size=zshape)
            got, got_z = iir.lfilter(b, a, x, axis=axis, zi=zi)
            want, want_z = signal.lfilter(b, a, x, axis=axis, zi=zi)
            assert np.array_equal(got, want) and np.array_equal(got_z, want_z)
    x = rng.normal(size=(300, 2))
    for b, a in (([0.0, 0.3], [1.0, -0.7]), ([0.2], [1.0, -0.8]), ([0.5, 0.25, 0.1], [2.0, -0.4]), ([3.0], [1.5])):
        assert np.array_equal(iir.lfilter(b, a, x, axis=0), signal.lfilter(b, a, x, axis=0)), (b, a)


def test_lfilter_refuses_a_state_that_does_not_fit():
    with pytest.raises(ValueError, match="initial state"):
        iir.lfilter([1.0, 0.5], [1.0, -0.5], np.zeros((10, 2)), axis=0, zi=np.zeros((2, 2)))


def test_the_frequency_response_is_scipys():
    for order, wn in ((4, 0.1), (4, 0.02), (2, 0.6)):
        b, a = signal.butter(order, wn)
        w, h = iir.freqz(b, a, points=8192)
        want_w, want_h = signal.freqz(b, a, worN=8192)
        assert np.array_equal(w, want_w)
        assert np.max(np.abs(h - want_h)) < 1e-12


@pytest.mark.parametrize("nperseg", [16, 64, 100, 127, 256, 1024, 5000])
def test_welch_and_csd_are_scipys_within_rounding(nperseg):
    rng = np.random.default_rng(nperseg)
    x = rng.normal(size=3001).cumsum()
    y = 0.3 * x + rng.normal(size=x.size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns where the segment is longer than the signal
        want_f, want_p = signal.welch(x, fs=1000.0, nperseg=nperseg)
        want_fxy, want_pxy = signal.csd(x, y, fs=1000.0, nperseg=nperseg)
    f, p = spectral.welch(x, 1000.0, nperseg)
    fxy, pxy = spectral.csd(x, y, 1000.0, nperseg)
    assert np.array_equal(f, want_f) and np.array_equal(fxy, want_fxy)
    assert p.dtype == want_p.dtype and pxy.dtype == want_pxy.dtype
    assert np.max(np.abs(p - want_p)) <= 1e-12 * np.max(want_p)
    assert np.max(np.abs(pxy - want_pxy)) <= 1e-12 * np.max(np.abs(want_pxy))


def test_filtering_and_spectra_do_not_import_scipy_signal():
    code = (
        "import sys, numpy as np\n"
        "from servobench.bench.identify.derivative import lowpass, differentiate_position\n"
        "from servobench.bench.diagnose.floor import derivative_gain\n"
        "from servobench.bench.dsp.spectral import csd, welch\n"
        "x = np.cumsum(np.random.default_rng(0).normal(size=2000))\n"
        "lowpass(x, 1000.0); differentiate_position(x, 1000.0); derivative_gain(1000.0, 50.0)\n"
        "welch(x, 1000.0, 256); csd(x, x[::-1], 1000.0, 256)\n"
        "print(sorted(m for m in sys.modules if m.startswith('scipy.signal')))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout
