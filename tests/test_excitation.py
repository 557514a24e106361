"""Excitation design: binary levels, periodicity, power on the lines, validation, metadata round trip."""

import numpy as np
import pytest

from servobench.bench.procedure.excitation import (
    ExcitationDesign,
    binary_period,
    default_freqs,
    design_excitation,
    design_from_metadata,
    freqs_around,
    make_design,
)
from servobench.errors import LogFormatError, UsageError


def test_default_design_is_binary_periodic_and_scaled():
    d = make_design(2.5)
    e = design_excitation(d)
    assert set(np.unique(e.u1)) == {-2.5, 2.5}
    np.testing.assert_allclose(e.u2, 0.9 * e.u1)
    n = d.samples_per_period
    assert len(e.u1) == d.periods * n
    for k in range(1, d.periods):
        np.testing.assert_array_equal(e.u1[k * n : (k + 1) * n], e.u1[:n])


def test_power_concentrates_on_the_lines():
    d = make_design(1.0)
    period, share = binary_period(d.samples_per_period, d.lines)
    spec = np.abs(np.fft.rfft(period)) ** 2
    measured = spec[d.lines].sum() / spec[1:].sum()
    assert share == pytest.approx(measured)
    assert share > 0.65  # a plain sign of a multisine gets about 0.65
    # every wanted line carries power
    assert np.min(spec[d.lines]) > 0.05 * np.max(spec[d.lines])


def test_default_lines_are_harmonics_below_fs_over_20():
    freqs = default_freqs(1000.0, 4000)
    f0 = 0.25
    assert freqs[0] == pytest.approx(f0)
    assert max(freqs) <= 40.0 + 1e-9
    for f in freqs:
        assert f / f0 == pytest.approx(round(f / f0))
    assert len(set(freqs)) == len(freqs) > 8


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"amplitude": 0.0}, "amplitude"),
        ({"amplitude": -1.0}, "amplitude"),
        ({"ratio": 1.0}, "ratio"),
        ({"ratio": 0.0}, "ratio"),
        ({"fs_hz": 0.0}, "fs"),
        ({"periods": 1}, "periods"),
        ({"freqs_hz": (0.3,)}, "multiple"),
        ({"freqs_hz": (-1.0,)}, "> 0"),
        ({"freqs_hz": (600.0,)}, "Nyquist"),
        ({"freqs_hz": (1.0, 1.0)}, "repeat"),
        ({"period_s": 0.001}, "fewer than 4"),
    ],
)
def test_bad_options_raise_usage_error(kwargs, message):
    args = {"amplitude": 1.0, **kwargs}
    amp = args.pop("amplitude")
    with pytest.raises(UsageError, match=message):
        make_design(amp, **args)


def test_metadata_round_trip():
    d = make_design(3.0, ratio=0.8, fs_hz=500.0, periods=5, period_s=2.0, freqs_hz=(0.5, 1.0, 7.5))
    meta = {
        k: (",".join(map(str, v)) if isinstance(v, list) else str(v))
        for k, v in d.metadata().items()
    }
    back = design_from_metadata(meta, 500.0)
    assert back == d
    assert design_from_metadata({}, 1000.0) is None
    with pytest.raises(LogFormatError):
        design_from_metadata({"samples_per_period": "x", "freqs": "1"}, 1000.0)


def test_redesign_centres_lines_on_the_corner():
    freqs = freqs_around(1.6, 1000.0, 4000)
    assert min(freqs) <= 0.25 and max(freqs) >= 15.0
    ExcitationDesign(1000.0, 4000, 4, freqs, 1.0)  # valid harmonics
