"""The identification plots: the friction map through sensor noise, the FRF's spread and friction
bias, and units on every axis.

Peers: the simulated plant's own parameters (the Coulomb levels the map must
show), the analytic spread of a DFT line under white sensor noise, and the
plant itself through the differential FRF (what the friction bias must be).
"""

from __future__ import annotations

import math
import re
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from servobench.bench.identify.auto import identify
from servobench.bench.procedure.excitation import make_design
from servobench.bench.report import plots
from servobench.bench.report.plot_data import frf_evidence, friction_map
from servobench.bench.testing.synthetic import simulate_experiment
from servobench.sim_backend.physics.plant import PlantParams
from servobench.units import LINEAR, ROTARY, SignalUnits

TRUE = PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4)


@cache
def _log(amplitude: float, noise: float, periods: int = 4, with_velocity: bool = True):
    design = make_design(amplitude, period_s=2.0, periods=periods)
    return simulate_experiment(TRUE.with_changes(noise=noise, seed=3), design, with_velocity=with_velocity)


@cache
def _result(amplitude: float, noise: float = 0.0, method: str = "auto", units: SignalUnits = ROTARY,
            periods: int = 4, with_velocity: bool = True):  # fmt: skip
    log = _log(amplitude, noise, periods, with_velocity)
    return identify(replace(log, metadata={**log.metadata, **units.as_metadata()}), method)


def test_friction_map_shows_the_coulomb_levels_through_sensor_noise():
    result = _result(1.0, noise=0.01)
    m = result.model
    # the raw sampled force u - M dv/dt - B v: the noise swamps a friction of 0.4-0.5
    run = result.verification.runs[0]
    a = math.exp(-m.B * 1e-3 / m.M)
    raw = run.u[:-1] - (run.v[1:] - a * run.v[:-1]) * m.B / (1 - a)
    assert np.std(raw) > 2 * TRUE.coulomb_pos
    fm = friction_map(result)
    moving = np.abs(fm.v_centre) > 0.25 * np.max(np.abs(fm.v_centre))
    assert np.count_nonzero(moving & (fm.v_centre > 0)) >= 5 and np.count_nonzero(moving & (fm.v_centre < 0)) >= 5
    truth = np.where(fm.v_centre > 0, TRUE.coulomb_pos, -TRUE.coulomb_neg)
    assert np.max(np.abs(fm.force_mean[moving] - truth[moving])) < 0.05
    assert np.max(fm.force_std[moving]) < 0.15  # the spread shown: a few hundredths, not +-6
    assert np.all(fm.count >= 20) and fm.cutoff_hz == pytest.approx(50.0)


def test_frf_spread_is_the_sensor_noise_over_the_periods():
    sigma = 0.01
    result = _result(2.0, noise=sigma, method="sidbe", periods=7)
    ev = frf_evidence(result)
    n = result.verification.runs[0].u.size // 7
    # a DFT line (divided by n) of white noise has E|X|^2 = sigma^2 / n; two runs differ
    frf = result.frf
    du = np.abs(frf.U1 - frf.U2)
    per_period = math.sqrt(2.0 / n) * sigma / du
    expected = per_period / math.sqrt(ev.periods)
    ratio = ev.std_error / expected
    assert ev.periods == 6 and 0.75 < np.median(ratio) < 1.3
    assert np.array_equal(ev.measured, frf.G)


def test_friction_bias_of_the_differential_frf_is_predicted_at_low_amplitude():
    result = _result(1.0)
    assert result.method == "joint"  # the friction-aware estimate: the exact plant
    low = frf_evidence(result)
    off = np.abs(low.measured - low.linear) / np.abs(low.linear)
    assert np.max(off) > 0.10  # at +-1 the measured points leave the linear block ...
    # ... and the exact model simulated with its friction lands on them
    assert np.max(np.abs(low.with_friction - low.measured) / np.abs(low.measured)) < 0.01
    assert low.biased
    high = frf_evidence(_result(60.0))
    assert not high.biased
    assert np.max(np.abs(high.measured - high.linear) / np.abs(high.linear)) < 0.01


def _labels(fig) -> list[str]:
    out = [fig._suptitle.get_text()] if fig._suptitle else []
    for ax in fig.axes:
        out += [ax.get_xlabel(), ax.get_ylabel(), ax.get_title()]
        out += [t.get_text() for t in ax.texts]
        legend = ax.get_legend()
        out += [t.get_text() for t in legend.get_texts()] if legend else []
    return [t for t in out if t]


@pytest.mark.parametrize(
    ("units", "v", "u", "gain"),
    [(ROTARY, "rad/s", "N m", "rad/(N m s)"), (LINEAR, "m/s", "N", "m/(N s)"),
     (SignalUnits(), "velocity unit", "command unit", "(velocity unit)/(command unit)")],
)  # fmt: skip
def test_every_axis_names_its_unit(units, v, u, gain):
    result = _result(1.0, units=units)
    friction = plots.friction_figure(result).axes[0]
    assert friction.get_xlabel().endswith(f"[{v}]") and friction.get_ylabel().endswith(f"[{u}]")
    frf = plots.frf_figure(result)
    assert frf.axes[0].get_ylabel() == f"|G| [{gain}]" and frf.axes[1].get_xlabel() == "frequency [Hz]"
    assert all(ax.get_ylabel() == f"v [{v}]" for ax in plots.time_figure(result).axes)
    texts = [t for fig in (plots.friction_figure(result), frf) for t in _labels(fig)]
    assert not [t for t in texts if re.search(r"\[units|units/s|command units", t)]
    assert all(f"[{v}]" in c or f"[{u}]" in c or "1/(M s + B)" in c for c in plots.captions(result).values())


def test_the_frf_explains_its_friction_bias_on_the_plot():
    note = [t for t in _labels(plots.frf_figure(_result(1.0))) if t.startswith("Friction bias")]
    assert len(note) == 1 and "±1 N m" in note[0] and "does not cancel" in note[0]
    assert not [t for t in _labels(plots.frf_figure(_result(60.0))) if t.startswith("Friction bias")]


def test_write_plots_writes_decodable_pngs_with_captions(tmp_path):
    import matplotlib.image

    result = _result(1.0, noise=0.01)
    written = plots.write_plots(result, tmp_path)
    assert [p.name for p in written] == ["frf.png", "time.png", "friction.png"]
    for path in written:
        image = matplotlib.image.imread(path)
        assert image.shape[0] > 300 and image.shape[1] == 800 and image.std() > 0.01
    assert set(plots.captions(result)) == {p.name for p in written}


def test_a_position_only_log_gets_its_frf_without_a_band(tmp_path):
    result = _result(2.0, with_velocity=False)
    ev = frf_evidence(result)
    assert ev.std_error is None and ev.with_friction is None  # the FRF was measured on position
    assert plots.plot_frf(result, tmp_path / "frf.png").is_file()
    note = [t for t in _labels(plots.frf_figure(result)) if "friction bias" in t.lower()]
    assert len(note) == 1 and note[0].startswith("Possible friction bias") and "measured on position" in note[0]
