"""The timing figure of an identification: how well the host kept time, and what it costs the model.

A real-time log (``pace = real``) states where its instants come from
(``# clock_source = drive | kernel | host``), each sample's timing
uncertainty (column ``t_unc``, the half-width of the interval known to hold
its instant), and the host's cycle in its trailer (``host_jitter_p50_s``,
``host_jitter_p99_s``, ``host_jitter_max_s``, ``missed_cycles``,
``late_cycles``). :func:`timing_figure` turns them into a
:class:`TimingFigure` with the model error this timing predicts:

* **how** -- the model is identified again :data:`DRAWS` times with every
  instant moved at random (an explicit seeded generator) by the estimator
  that gave it. The move is as large as the log shows its instants really
  stray: ``t_unc`` bounds each instant, but a drive that samples at a steady
  point of a wide bracket strays far less (a constant delay moves every
  instant and command alike), so the scatter is read from the model's
  residuals in the transients
  (:func:`~servobench.bench.identify.joint.instant_scatter_s`,
  ``instant_scatter_s`` in the figure) and each instant moves by a normal
  draw of that spread, never beyond ``t +- t_unc``; where the residuals show
  no scatter to read, uniformly within ``t +- t_unc``. Served Modbus RTU
  without its time stamp at 50 Hz: brackets 1.2 ms wide either way, a
  scatter of 0.03 ms read, a predicted M error of 0.1 % against the 0.1 %
  measured (the bracket alone predicted 1.1 %). Where each command travels
  ahead of its sample in a request of its own (a command lead: ODrive serial)
  and no tick grid was located, each draw also moves where each command acts,
  apart from its row's instant: the drive acts at the tick after the command's
  arrival and samples at the tick before the query's, so the rows' delays
  spread (served at a 0.125 ms tick: predicted 0.21 % for a true 0.29 % before
  the actions moved). How far the actions stray is read at the command's changes
  (:func:`~servobench.bench.identify.joint.action_scatter_s`,
  ``action_scatter_s`` in the figure), each change's residual over the
  sensitivity of its interval to the action's instant: the scatter read
  against the acceleration takes an action's error for a sample's and read
  0.11-0.12 ms where the changes read 0.056-0.058 ms (three served logs
  at a 0.125 ms tick predicted 0.63-0.69 % at two sigma for errors of
  0.03-0.07 % (the worst parameter), now 0.25-0.26 %). The re-run estimator: an output-error model is refined again from itself on each moved copy;
  any other by the joint estimator's exact pair regression
  (:func:`~servobench.bench.identify.joint.pair_regression`, weighted by the
  timing uncertainty), compared with the same regression on the instants as
  logged. The root mean square
  of the relative change of each parameter over the draws is its predicted
  timing error [%] (1 sigma). The draws cover the excited band as the log
  does: they perturb the very samples the model comes from.
* Where the output-error refinement weighted its samples by their timing
  (:func:`~servobench.bench.identify.joint._sample_weights`), the change of
  each parameter when they are weighted equally is added in quadrature
  (:func:`weighting_pct`; the delay's change to its timing share): both are
  consistent where the timing is as the scatter says, so where they part the
  log holds timing errors the draws do not reproduce (a few exchanges held up
  by a busy machine).
* Where the timing moved the delay (its share of the delay's sigma), the
  output-error refinement is run again with the delay held that far above and
  below its own value (:func:`delay_held_pct`), and each parameter's change per
  that share is added in quadrature: random instants move the delay and the
  time constant together as the draws do, but a timing that misleads the delay
  as a whole moves M along the fit's trade between the two (served Modbus RTU
  without stamps at a 0.125-0.25 ms tick: M 0.045-0.075 % off against 0.043-0.072 %
  predicted at two sigma before, 0.060-0.085 % with it). Not behind a command's
  lead on a located grid (ODrive serial: a command sent ahead of its query):
  there each draw places every read in doubt by its odds under the model
  (:data:`METHOD_LEAD_POSTERIOR`), its sample and its action, so the draws
  hold the timing's whole effect, and the delay is the mean of the rows'
  placed delays, which the few reads in doubt move while the actions stay;
  held apart, every action moved with it, it predicted 0.87-10.7 % at two
  sigma for seven served logs 0.00004-0.18 % off, now 0.12-0.43 %.
* Where the reads were moved onto a located grid on which each command acts a
  whole number of ticks after its sample (one request carrying both), the
  delay's distance to the nearer whole tick count joins its timing share
  (:func:`~servobench.bench.identify.drive_grid.off_grid_s`), before the
  delay is held apart: a model acting between two ticks holds misplaced
  reads, which neither the fit's sigma nor the draws see.
* A drive time stamp (``clock_source = drive``) has no interval: the
  timing's share is 0, whatever the host's jitter (the instants are exact).
* The drive's own clock: the model carries the drive's action delay
  (``delay_s``, identified with the plant, its 1 sigma from the same fit) and
  the figure states it beside the tick the stamps show (``drive_tick_s``,
  ``repeated_samples``, ``skipped_ticks``, ``late_samples`` from the log's trailer). Each
  parameter's predicted error is the timing's share and the model's own
  statistical 1 sigma (whose fit holds the delay free, so the delay's
  uncertainty is in it) added in quadrature. The delay's own predicted error
  (``delay_error_s``, the sigma the result states for ``delay_s``) is its
  fit's 1 sigma and the rms change of the delay over the same draws, in
  quadrature: the fit's sigma alone did not hold (a fresh-clone suite gave
  served Modbus RTU at a 0.25 ms tick without stamps 0.649 +- 0.045 ms
  against 0.25, the reads misplaced on the located grid; ODrive serial at
  1 ms 0.552 +- 0.001 ms against 0.492). Where the pairs placed the reads on
  a grid (the simulation's or the pairs' own), each
  draw places them by a draw from the pairs' posterior
  (:data:`METHOD_POSTERIOR`): a read the pairs decide keeps its tick, one in
  doubt moves as often as its odds say. Placed by the grid alone, each read
  anywhere in its bracket, the draws moved reads the pairs had decided: Modbus
  RTU at a 1 ms tick without stamps, on four suites' logs, stated the delay
  +- 0.13 to 0.88 ms for delays within 0.005 ms of the record; now +- 0.003 to
  0.007 ms. Where the delay's fit sigma is
  more than :data:`DELAY_SEPARABLE_SHARE` of the longer of a cycle and the
  time constant, the data cannot tell the delay from the plant's lag: the
  figure is not within accuracy and its first lines say what to change.

A figure whose largest parameter error, at :data:`COVERAGE` sigma, exceeds the
stated accuracy (:data:`ACCURACY_PCT`) is not :attr:`TimingFigure.within_accuracy`; its
:meth:`TimingFigure.advice` says what to change: a lower ``--fs``, a free
core, a drive that time-stamps its samples.
"""

from __future__ import annotations

import contextlib
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from servobench.bench.identify.dataset import Dataset
from servobench.bench.identify.drive_grid import off_grid_s
from servobench.bench.identify.drive_rate import quantised_rate_std
from servobench.bench.identify.estimate import MethodEstimate
from servobench.bench.model.servo import DELAY_KEY, STD_KEYS
from servobench.errors import IdentificationError

#: Accuracy the model states for its parameters [%]: timing that predicts more is reported.
ACCURACY_PCT = 1.0
#: Coverage factor of that statement: the predicted 1 sigma times this within the accuracy (two
#: sigma, 95 % of a normal error). At one sigma a run said "within accuracy" with M 1.15 % off and
#: 0.65 % predicted (a fresh-clone suite, served Modbus RTU at a 0.25 ms tick, host stalls of 37 ms).
COVERAGE = 2.0
#: Re-identifications with perturbed instants.
DRAWS = 4
#: Seed of the perturbations (the figure is reproducible from the log).
SEED = 22
#: Metadata keys of the host's cycle (the runner's trailer).
CYCLE_KEYS = ("host_jitter_p50_s", "host_jitter_p99_s", "host_jitter_max_s", "missed_cycles",
              "late_cycles", "t_unc_p50_s", "t_unc_p99_s", "t_unc_max_s")  # fmt: skip
METHOD = (
    f"re-identification ({DRAWS} draws, by the estimator that gave the model) with every instant "
    "moved at random by the scatter the residuals show (instant_scatter_s, normal), never beyond "
    "its uncertainty t_unc; rms relative change, 1 sigma, with the model's own 1 sigma in quadrature"
)
#: Behind a command's lead, each command's action moved by the scatter its changes show.
METHOD_ACTIONS = (
    "; behind the command's lead, each command's action moved apart by the scatter the residuals at "
    "its changes show (action_scatter_s, normal)"
)
#: The method where the drive stamps its samples (the instants are exact).
METHOD_STAMPS = "drive time stamps: exact instants; the model's own 1 sigma"
#: The delay counts as inseparable from the plant's lag when its 1 sigma exceeds this share of
#: the longer of a cycle and the time constant.
DELAY_SEPARABLE_SHARE = 0.25
#: The method where the samples were moved onto the drive's tick grid located on the host's clock.
METHOD_GRID = (
    f"re-identification ({DRAWS} draws) with every read placed at random in its bracket t +- t_unc "
    "and moved onto the drive's tick grid again; rms relative change, 1 sigma, with the model's own "
    "1 sigma in quadrature"
)
#: The method where the reads were placed on the drive's tick grid by the model's pairs.
METHOD_POSTERIOR = (
    f"re-identification ({DRAWS} draws) with the reads placed on the drive's tick grid by a draw "
    "from the posterior of the model's pairs; rms relative change, 1 sigma, with the model's own "
    "1 sigma in quadrature"
)
#: The method where a command's lead left reads in doubt, each placed by its odds under the model.
METHOD_LEAD_POSTERIOR = (
    f"re-identification ({DRAWS} draws) with each read in doubt (a command sent ahead of its query) "
    "placed on the drive's tick grid by a draw from its odds under the model's simulation; rms "
    "relative change, 1 sigma, with the model's own 1 sigma in quadrature"
)
#: Added to the method where the delay is the mean of rows placed behind a command's lead.
METHOD_LEAD_RESOLUTION = (
    "; and, in quadrature with the delay's timing share, one command change's tick over the "
    "changes the delay is the mean of"
)
#: Added to the method where the grid alone places the reads behind a command's lead.
METHOD_PLACED_DELAY = (
    "; and, in quadrature with the delay's timing share, the rms departure from it of the mean "
    "delay the grid alone places the reads at, each read anywhere in its bracket"
)
#: Draws of :func:`placed_delay_spread_s` (a placement each, no identification).
PLACED_DRAWS = 16
#: Added to the method where the delay held apart moved the other parameters (:func:`delay_held_pct`).
METHOD_DELAY_HELD = (
    "; and, in quadrature, the change of each parameter when the delay is held its timing 1 sigma "
    "from its own value"
)
#: Added to the method where the model was identified on a located grid it must act on in whole
#: ticks (:func:`~servobench.bench.identify.drive_grid.off_grid_s`).
METHOD_OFF_GRID = (
    "; and, in quadrature with the delay's timing share, how far the delay lies from the whole "
    "ticks after its sample that the located grid has each command act"
)
#: Added to the method where the output-error refinement weighted its samples by their timing.
METHOD_WEIGHTING = "; and, in quadrature, the change of each parameter when the output-error samples are weighted equally"
#: The method where the residuals show no scatter to read.
METHOD_BOUND = (
    f"re-identification ({DRAWS} draws, by the estimator that gave the model) with every instant "
    "moved at random within its uncertainty t_unc; rms relative change, 1 sigma, with the model's "
    "own 1 sigma in quadrature"
)


@dataclass(frozen=True)
class TimingFigure:
    """How well the instants of a real-time log are known, and the model error that predicts.

    Attributes
    ----------
    clock_source : str
        ``drive``, ``kernel`` or ``host``.
    cycle : mapping of str to float
        The host's cycle from the log trailer (:data:`CYCLE_KEYS`, seconds and counts).
    fs_hz : float
        The log's cycle rate [Hz].
    model_error_pct : mapping of str to float
        Predicted timing error of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg`` [%], 1 sigma.
    method : str
        How the error was predicted.
    accuracy_pct : float
        The accuracy the model states [%].
    """

    clock_source: str
    cycle: Mapping[str, float]
    fs_hz: float
    model_error_pct: Mapping[str, float] = field(default_factory=dict)
    method: str = METHOD
    accuracy_pct: float = ACCURACY_PCT
    time_constant_s: float = math.nan  #: the model's ``M / B`` [s]
    link_max_hz: float = math.nan  #: the rate the link carries, from the log [Hz]
    #: How far the instants stray, 1 sigma each, as the residuals show [s] (NaN: not read).
    instant_scatter_s: float = math.nan
    #: Behind a command's lead, how far each command's action strays from where the model has
    #: it, 1 sigma, as the residuals at its changes show [s] (NaN: not read, or no lead).
    action_scatter_s: float = math.nan
    #: The drive's identified action delay and its statistical 1 sigma [s] (the model's ``delay_s``
    #: and the fit's sigma).
    delay_s: float = 0.0
    delay_std_s: float = math.nan
    #: How far the draws moved the delay, rms [s]: its timing share (0 where the instants are exact).
    delay_timing_std_s: float = 0.0
    #: The drive's control tick read from its time stamps [s] (NaN: no stamps, or no grid in them).
    drive_tick_s: float = math.nan
    #: Reads that returned a tick already read, and ticks that passed unread (stamped logs).
    repeated_samples: int = 0
    skipped_ticks: int = 0
    #: Rows whose command took force before their sample (a later tick's sample read: the host
    #: woke late; the log's ``t_act`` says where, and the model takes each from there).
    late_samples: int = 0
    #: The model's own statistical 1 sigma of each parameter [%], folded into the prediction.
    statistical_pct: Mapping[str, float] = field(default_factory=dict)
    #: The drive clock's drift against the host's and its 1 sigma [ppm], read from its stamps
    #: against the host's instants (:mod:`~servobench.bench.identify.drive_rate`; the stamps were
    #: taken onto the host's seconds where it is significant); NaN: not read.
    drive_drift_ppm: float = math.nan
    drive_drift_std_ppm: float = math.nan

    @property
    def model_error_max_pct(self) -> float:
        values = [v for v in self.model_error_pct.values() if math.isfinite(v)]
        return max(values) if values else 0.0

    @property
    def model_error_bound_pct(self) -> float:
        """The largest parameter error the figure allows at its coverage [%]: :data:`COVERAGE`
        times :attr:`model_error_max_pct` (two sigma, 95 % of a normal error). What "within
        accuracy" is judged by, and the figure a prediction is checked against: at one sigma an
        honest prediction falls short of its error in a third of the runs (the EtherCAT slave at
        a 1 ms tick with stamps: 0.0227 % off with 0.0225 % predicted, the model's own sigma)."""
        return COVERAGE * self.model_error_max_pct

    @property
    def delay_error_s(self) -> float:
        """The delay's predicted error [s], 1 sigma: its timing share and the fit's own sigma in
        quadrature (the sigma the model states for ``delay_s``; NaN where the fit's is unknown)."""
        return math.hypot(self.delay_std_s, self.delay_timing_std_s)

    @property
    def within_accuracy(self) -> bool:
        return self.model_error_bound_pct <= self.accuracy_pct and self.delay_separable

    @property
    def delay_separable(self) -> bool:
        """False when the data cannot tell the drive's delay from the plant's lag: the delay's
        1 sigma exceeds :data:`DELAY_SEPARABLE_SHARE` of a cycle and of the time constant."""
        sd = self.delay_std_s
        if not math.isfinite(sd):
            return True
        return sd <= DELAY_SEPARABLE_SHARE * max(1.0 / self.fs_hz, self.time_constant_s)

    def advice(self) -> list[str]:
        """What to change, most effective first (empty when within accuracy)."""
        if self.within_accuracy:
            return []
        if self.time_constant_s < 2.0 / self.fs_hz:  # the cycle is long against the plant
            carries = f" (the link carries {self.link_max_hz:.0f} Hz)" if math.isfinite(self.link_max_hz) else ""
            tips = [f"raise --fs where the link allows{carries}: the plant's time constant "
                    f"{self.time_constant_s * 1e3:.3g} ms is short against the {1e3 / self.fs_hz:.3g} ms "
                    "cycle, so the instants' uncertainty weighs on M"]  # fmt: skip
        else:
            lower = _nice_below(self.fs_hz / 2)
            tips = [f"lower --fs (e.g. --fs {lower:g}: longer cycles, the same timing error weighs less)"]
        load = _load_average()
        tips.append(
            "free a core for the host" + (f" (load average {load:.1f})" if load is not None else "")
        )
        if self.clock_source != "drive":
            tips.append("use a drive that time-stamps its samples (CiA 402 0x1013 mapped, a Modbus "
                        "map with a time-stamp register): its instants are exact")  # fmt: skip
        return tips

    def warning_lines(self) -> list[str]:
        """The lines a summary starts with when the timing takes the model outside its accuracy."""
        if self.within_accuracy:
            return []
        if not self.delay_separable:
            return [
                f"WARNING: the drive's action delay ({self.delay_s * 1e3:.3g} ms +- "
                f"{self.delay_std_s * 1e3:.2g} ms) cannot be told from the plant's lag (time constant "
                f"{self.time_constant_s * 1e3:.3g} ms) at {self.fs_hz:g} Hz: M and B may be off",
                "to change: raise --fs where the link allows, or excite faster lines "
                "(--fmax closer to the time constant's corner), so delay and lag differ in phase",
            ]
        worst = max(self.model_error_pct, key=lambda k: self.model_error_pct[k])
        c = self.cycle
        first = (
            f"WARNING: timing takes the model outside its stated accuracy: {worst} may be off by "
            f"{COVERAGE * self.model_error_pct[worst]:.2g} % ({COVERAGE:g} sigma; stated accuracy "
            f"{self.accuracy_pct:g} %), "
            f"clock_source = {self.clock_source}, instants uncertain by up to "
            f"{_ms(c.get('t_unc_p99_s'))} ms (p99), host jitter p99 {_ms(c.get('host_jitter_p99_s'))} ms, "
            f"{int(c.get('missed_cycles', 0) or 0)} missed cycles"
        )
        return [first, "to change: " + "; ".join(self.advice())]

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"clock_source": self.clock_source}
        for key in CYCLE_KEYS:
            value = _finite(self.cycle.get(key, math.nan))
            counted = key.endswith("_cycles") and value is not None
            out[key.replace("host_", "")] = int(value) if counted else value
        out.update(
            model_error_pct={k: _finite(v) for k, v in self.model_error_pct.items()},
            model_error_max_pct=_finite(self.model_error_max_pct),
            model_error_bound_pct=_finite(self.model_error_bound_pct),
            coverage_sigma=COVERAGE,
            model_error_method=self.method,
            instant_scatter_s=_finite(self.instant_scatter_s),
            action_scatter_s=_finite(self.action_scatter_s),
            delay_s=_finite(self.delay_s),
            delay_std_s=_finite(self.delay_std_s),
            delay_error_s=_finite(self.delay_error_s),
            drive_tick_s=_finite(self.drive_tick_s),
            drive_drift_ppm=_finite(self.drive_drift_ppm),
            drive_drift_std_ppm=_finite(self.drive_drift_std_ppm),
            repeated_samples=int(self.repeated_samples),
            skipped_ticks=int(self.skipped_ticks),
            late_samples=int(self.late_samples),
            statistical_pct={k: _finite(v) for k, v in self.statistical_pct.items()},
            delay_separable=self.delay_separable,
            accuracy_pct=self.accuracy_pct,
            within_accuracy=self.within_accuracy,
            advice=self.advice(),
        )
        return out


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def _ms(value: float | None) -> str:
    return "?" if value is None or not math.isfinite(value) else f"{value * 1e3:.3g}"


def _nice_below(fs_hz: float) -> float:
    decade = 10.0 ** math.floor(math.log10(max(fs_hz, 1.0)))
    return max(m * decade for m in (1.0, 2.0, 2.5, 5.0) if m * decade <= max(fs_hz, 1.0))


def _load_average() -> float | None:
    try:
        return os.getloadavg()[0]
    except OSError:
        return None


def _number(text: str | None) -> float:
    try:
        return float(text) if text is not None else math.nan
    except ValueError:
        return math.nan


def timing_figure(
    metadata: Mapping[str, str],
    data: Dataset,
    estimate: MethodEstimate,
    regrid: Callable[[Dataset], Dataset] | None = None,
    logged: Dataset | None = None,
    placements: Callable[[Dataset, np.random.Generator], Dataset] | None = None,
    grid_tick_s: float | None = None,
    lead_tick_s: float | None = None,
    placed_delay: Callable[[Dataset], float] | None = None,
    free_delay_s: float | None = None,
) -> TimingFigure | None:
    """The timing figure of a real-time log and the model identified from it.

    ``regrid`` and ``logged``: the samples of ``data`` were moved onto the drive's
    tick grid located on the host's clock
    (:mod:`~servobench.bench.identify.drive_grid`); ``logged`` holds them as
    logged. The draws then place each read anywhere in its bracket ``t +- t_unc``
    (where the request really reached the drive) and move it onto the grid again,
    so a read that could have landed on either of two ticks does so at random.
    ``placements`` (with ``logged``): instead, each draw places the reads of ``logged``
    anew by a draw from the posterior of the pairs that placed them
    (:func:`~servobench.bench.identify.pair_placement.place_by_pairs` with a generator): a
    read the pairs decide keeps its tick, one in doubt moves as often as its odds say; behind a
    command's lead (``lead_tick_s`` given), by each read's odds under the model's simulation.
    ``lead_tick_s``: the reads were moved onto a grid of that tick behind a command's lead; the
    delay, the mean of the rows' placed delays over the command changes, is known to one change's
    tick (:func:`lead_resolution_s`), which joins its timing share. ``placed_delay``: the mean
    delay the grid alone places a dataset's reads at; where each read lands anywhere in its
    bracket, its spread (:func:`placed_delay_spread_s`) joins the delay's timing share too.
    ``grid_tick_s``: the reads were moved onto a grid of that tick on which each command acts a
    whole number of ticks after its sample (one request carries both); the delay's departure from
    that (:func:`~servobench.bench.identify.drive_grid.off_grid_s`) joins its timing share.
    ``free_delay_s``: there, the estimator held the delay at the grid's whole ticks
    (:attr:`~servobench.bench.identify.dataset.Dataset.delay_held_s`); the departure of the
    delay the log gives left free [s] is what joins it.

    None for a log without ``clock_source`` (lock-step streaming, older logs,
    files of other tools): its instants are the nominal grid or the drive's.
    """
    source = metadata.get("clock_source", "").strip()
    if not source:
        return None
    cycle = {key: _number(metadata.get(key)) for key in CYCLE_KEYS}
    timing = {k: 0.0 for k in STD_KEYS}
    delay_moved = 0.0
    scatter, action, method = math.nan, math.nan, METHOD_STAMPS
    m = estimate.model
    if data.timing_uncertain and not data.derived:
        from servobench.bench.identify.joint import instant_scatter_s

        scatter = instant_scatter_s(data, m)
        if placements is not None and logged is not None:
            timing, delay_moved = perturbed_spread_pct(logged, estimate, placements=placements)
            method = METHOD_POSTERIOR if lead_tick_s is None else METHOD_LEAD_POSTERIOR
        elif regrid is not None and logged is not None:
            timing, delay_moved = perturbed_spread_pct(logged, estimate, regrid=regrid)
            method = METHOD_GRID
        else:
            if data.min_delay_s < 0:  # a command lead: where each command acts strays on its own
                from servobench.bench.identify.joint import action_scatter_s

                action = action_scatter_s(data, m)
            timing, delay_moved = perturbed_spread_pct(data, estimate, scatter_s=scatter,
                                                       action_scatter_s=action)  # fmt: skip
            method = METHOD if math.isfinite(scatter) else METHOD_BOUND
            if math.isfinite(action):
                method += METHOD_ACTIONS
        weighting = weighting_pct(data, estimate)
        if weighting is not None:
            timing = {k: math.hypot(timing[k], weighting[0][k]) for k in STD_KEYS}
            delay_moved = math.hypot(delay_moved, weighting[1])
            method += METHOD_WEIGHTING
        if grid_tick_s is not None and grid_tick_s > 0:
            free = m.delay_s if free_delay_s is None else free_delay_s
            delay_moved = math.hypot(delay_moved, off_grid_s(free, grid_tick_s))
            method += METHOD_OFF_GRID
        if lead_tick_s is not None and lead_tick_s > 0:
            delay_moved = math.hypot(delay_moved, lead_resolution_s(data, lead_tick_s))
            method += METHOD_LEAD_RESOLUTION
        if placed_delay is not None and logged is not None:
            delay_moved = math.hypot(delay_moved, placed_delay_spread_s(logged, estimate, placed_delay, m.delay_s))
            method += METHOD_PLACED_DELAY
        # behind a command's lead each draw places every row's sample and action ticks anew, and
        # the delay is the mean of the rows' placed delays over the command changes, which moves
        # with the few rows in doubt (0.14 ms over the draws of a served ODrive log at a 2 ms tick)
        # while the actions stay where they were: the draws hold the timing's whole effect, and
        # the delay held apart, every action moved with it, no placement does (it predicted 3.5 %
        # of M for a model 0.0001 % off)
        split = placements is not None and lead_tick_s is not None
        held = None if split else delay_held_pct(data, estimate, delay_moved)
        if held is not None:
            timing = {k: math.hypot(timing[k], held[k]) for k in STD_KEYS}
            method += METHOD_DELAY_HELD
    statistical = {k: _relative_pct(estimate.std.get(k, math.nan), getattr(m, k)) for k in STD_KEYS}
    # the timing's share and the model's own statistical sigma, independent: added in quadrature
    error = {k: math.hypot(timing[k], statistical[k]) if math.isfinite(statistical[k]) else timing[k]
             for k in STD_KEYS}  # fmt: skip
    drift, drift_std = data.drive_drift_ppm
    # the time base's own error scales every time constant: M's [ppm -> %]. Stamps: the drive's
    # clock against the host's; reads moved onto a grid located on the host's clock: the grid's
    # drift, known to a tick over the run
    time_base_ppm = data.time_base_error_ppm
    if (regrid is not None or placements is not None) and logged is not None:
        time_base_ppm = max(time_base_ppm, *(1e6 * quantised_rate_std(s.t) for s in data.segments))
    error["M"] = math.hypot(error["M"], time_base_ppm * 1e-4)
    tau = m.M / m.B if m.B > 0 else math.inf
    return TimingFigure(source, cycle, data.fs_hz, error, method=method, time_constant_s=tau,
                        link_max_hz=_number(metadata.get("link_max_rate_hz")),
                        instant_scatter_s=scatter, action_scatter_s=action, delay_s=m.delay_s,
                        delay_std_s=float(estimate.std.get(DELAY_KEY, math.nan)),
                        delay_timing_std_s=delay_moved,
                        drive_tick_s=_number(metadata.get("drive_tick_s")),
                        repeated_samples=_count(metadata.get("repeated_samples")),
                        skipped_ticks=_count(metadata.get("skipped_ticks")),
                        late_samples=_count(metadata.get("late_samples")),
                        statistical_pct=statistical, drive_drift_ppm=drift,
                        drive_drift_std_ppm=drift_std)  # fmt: skip


def weighting_pct(data: Dataset, estimate: MethodEstimate) -> tuple[dict[str, float], float] | None:
    """Relative change [%] of each parameter, and the change of the delay [s], when
    ``estimate``'s output-error samples are weighted equally instead of by their timing
    (:func:`~servobench.bench.identify.joint.equally_weighted`); None where that does not apply.

    Both weightings are consistent where the model holds and the instants stray as the scatter
    says; where they part, the timing carries an error neither the draws nor the model's own
    sigma show, and the figure counts it. Measured on served Modbus RTU logs at 50 Hz without
    stamps (a 0.125-0.25 ms tick): the weighted model 0.03-0.06 % off (M), predicted 0.013-0.024 %
    by the draws and its own sigma; equal weights 0.06-0.2 % off there, and 1-2.7 % where two busy
    processes held up a few exchanges.
    """
    from servobench.bench.identify.joint import equally_weighted

    other = equally_weighted(data, estimate)
    if other is None:
        return None
    m = estimate.model
    pct = {k: abs(getattr(other, k) / getattr(m, k) - 1.0) * 100.0 if getattr(m, k) else 0.0 for k in STD_KEYS}
    return pct, abs(other.delay_s - m.delay_s)


def placed_delay_spread_s(logged: Dataset, estimate: MethodEstimate, placed_delay: Callable[[Dataset], float],
                          delay_s: float, draws: int = PLACED_DRAWS, seed: int = SEED) -> float:  # fmt: skip
    """RMS departure [s] from ``delay_s`` of the mean delay ``placed_delay`` gives the reads of
    ``logged`` moved anywhere in their brackets (a placement each, by the grid alone). Behind a
    command's lead the delay is a statistic of where the reads were placed: the simulation
    decides the reads in doubt, and a placement it decides with certainty can still be off by a
    share of a tick over many changes (a served ODrive log at a 0.25 ms tick: -0.004 ms against
    the drive's record of -0.102 ms, the draws by the reads' odds moving it 0.012 ms), which the
    brackets' own freedom shows."""
    rng = np.random.default_rng(seed)
    found = []
    for _ in range(draws):
        with contextlib.suppress(IdentificationError):
            moved = _moved_instants(logged, estimate, rng, math.nan, split=False, anywhere=True)
            found.append(placed_delay(moved) - delay_s)
    return float(np.sqrt(np.mean(np.square(found)))) if found else math.inf


def lead_resolution_s(data: Dataset, tick_s: float) -> float:
    """How well the mean of placed delays is known [s]: one command change's tick over the changes
    of every run. Behind a command's lead each change acts a whole number of ticks after its
    sample, and a change the simulation decides with certainty may still sit a tick off; the
    draws do not move it. A served ODrive log at a 2 ms tick: 1.690 ms against the drive's
    record of 1.661 ms over 58 changes (0.034 ms a change), with no read in doubt."""
    changes = sum(int(np.count_nonzero(np.diff(s.u))) + 1 for s in data.segments)
    return tick_s / max(changes, 1)


def delay_held_pct(data: Dataset, estimate: MethodEstimate, delay_moved_s: float) -> dict[str, float] | None:
    """Change [%] of each parameter per ``delay_moved_s`` [s] of the delay: half the difference
    between ``estimate``'s output-error refinement with the delay held ``delay_moved_s`` above
    and below its own (:func:`~servobench.bench.identify.joint.delay_held`); None where that does
    not apply or the timing moved the delay by nothing.

    The draws move the instants at random and see the delay and the other parameters move
    together as random instants move them; a timing that misleads the delay as a whole (where
    in its bracket a drive really took each request) moves the others along the fit's own
    trade between the delay and the time constant instead, which the draws do not follow.
    Measured on served Modbus RTU without stamps at a 0.125-0.25 ms tick (no grid located):
    M 0.045-0.075 % off where the draws and the model's own sigma predicted 0.022-0.036 % (1
    sigma), the delay 0.016-0.027 ms long against its stated 0.018-0.020 ms; held at the true
    delay M was 0.018-0.029 % off, and 1.6 % per millisecond of the delay moves it.
    """
    from servobench.bench.identify.joint import delay_held

    if not (math.isfinite(delay_moved_s) and delay_moved_s > 0):
        return None
    m = estimate.model
    held = delay_held(data, estimate, (m.delay_s - delay_moved_s, m.delay_s + delay_moved_s))
    if held is None:
        return None
    low, high = held
    span = delay_moved_s + min(delay_moved_s, m.delay_s - data.min_delay_s)  # the low end stops at the least delay
    if span <= 0:
        return None
    per_pct = 100.0 * delay_moved_s / span  # [%] of a parameter's relative change over the span
    return {k: abs(getattr(high, k) - getattr(low, k)) / abs(getattr(m, k)) * per_pct
            if getattr(m, k) else 0.0 for k in STD_KEYS}  # fmt: skip


def _relative_pct(std: float, value: float) -> float:
    try:
        return abs(float(std) / float(value)) * 100.0 if value else math.nan
    except (TypeError, ValueError):
        return math.nan


def _count(text: str | None) -> int:
    value = _number(text)
    return int(value) if math.isfinite(value) else 0


def perturbed_spread_pct(
    data: Dataset,
    estimate: MethodEstimate,
    draws: int = DRAWS,
    seed: int = SEED,
    scatter_s: float = math.nan,
    regrid: Callable[[Dataset], Dataset] | None = None,
    placements: Callable[[Dataset, np.random.Generator], Dataset] | None = None,
    action_scatter_s: float = math.nan,
) -> tuple[dict[str, float], float]:
    """RMS relative change [%] of each parameter when the instants move within ``t_unc``:
    by normal draws of ``scatter_s`` [s] clipped to ``t +- t_unc``, or uniformly within it
    when ``scatter_s`` is NaN; and the RMS change of the delay [s] (0 where the estimator holds
    the delay: the pair regression).

    The estimator of ``estimate`` is re-run: an output-error estimate is refined
    again from itself on each perturbed copy (the refinement alone, started where
    it ended); any other by the joint pair regression, compared with the same
    regression on the instants as logged. ``placements``: each draw is ``placements(data,
    generator)`` (the reads placed anew, their instants as logged) instead of moved instants.
    ``action_scatter_s``: behind a command's lead, how far each command's action strays apart
    from its row's instant (:func:`~servobench.bench.identify.joint.action_scatter_s`; NaN:
    by ``scatter_s`` too).
    """
    from servobench.bench.identify.joint import identify_joint, pair_regression

    rng = np.random.default_rng(seed)
    refine = estimate.estimator.endswith("output-error")
    model = estimate.model
    delay, tau = model.delay_s, model.time_constant_s
    if not refine:
        with contextlib.suppress(IdentificationError):  # the same estimator on the instants as logged
            model = pair_regression(data, delay, tau)
    nominal = np.array([model.M, model.B, model.coulomb_pos, model.coulomb_neg])
    split = data.min_delay_s < 0  # commands sent ahead of their sample, in separate requests
    changes, delays = [], []
    for _ in range(draws):
        try:
            if placements is not None:
                moved = placements(data, rng)
            else:
                moved = _moved_instants(data, estimate, rng, scatter_s, split, regrid is not None,
                                        action_scatter_s)  # fmt: skip
                if regrid is not None:
                    moved = regrid(moved)
            m = identify_joint(moved, start=estimate).model if refine else pair_regression(moved, delay, tau)
        except IdentificationError:
            continue
        values = np.array([m.M, m.B, m.coulomb_pos, m.coulomb_neg])
        with np.errstate(divide="ignore", invalid="ignore"):
            changes.append(np.where(nominal != 0, values / nominal - 1.0, 0.0))
        delays.append(m.delay_s - model.delay_s)
    if not changes:
        return {k: math.inf for k in STD_KEYS}, math.inf
    rms = np.sqrt(np.mean(np.square(changes), axis=0)) * 100.0
    delay_rms = float(np.sqrt(np.mean(np.square(delays))))
    return dict(zip(STD_KEYS, (float(x) for x in rms), strict=True)), delay_rms


def _moved_instants(data: Dataset, estimate: MethodEstimate, rng: np.random.Generator, scatter_s: float,
                    split: bool, anywhere: bool, action_scatter_s: float = math.nan) -> Dataset:  # fmt: skip
    """``data`` with every instant moved as :func:`perturbed_spread_pct` says: anywhere in its
    bracket (``anywhere``: the grid's draws), by a normal draw of ``scatter_s`` within it, or
    uniformly within it; with a command lead (``split``) each command's action apart as well, by
    ``action_scatter_s`` where it was read (else ``scatter_s``)."""
    segments = []
    for s in data.segments:
        if s.t_unc is None:
            segments.append(s)
            continue
        # a drive that samples at its own last tick widens each bracket by up to its tick,
        # which its action delay bounds
        reach = s.t_unc + max(estimate.model.delay_s, 0.0)
        if anywhere:  # the request reached the drive anywhere in its bracket
            t = s.t + rng.uniform(-1.0, 1.0, len(s)) * s.t_unc
        elif math.isfinite(scatter_s):
            t = s.t + np.clip(rng.normal(0.0, scatter_s, len(s)), -reach, reach)
        else:
            t = s.t + rng.uniform(-1.0, 1.0, len(s)) * reach
        dt = np.diff(t)
        if not np.all(dt > 0):  # overlapping intervals (not a runner's log): move less
            t = s.t + 0.5 * rng.uniform(-1.0, 1.0, len(s)) * np.minimum(
                s.t_unc, np.concatenate(([np.inf], np.diff(s.t))), )
            dt = np.diff(t)
        offsets = s.act_offset_s
        if split and not anywhere and math.isfinite(scatter_s):
            # the command travels in a request of its own: where it acts strays apart from
            # where its row's sample was taken (each at the drive's tick next to its arrival)
            spread = action_scatter_s if math.isfinite(action_scatter_s) else scatter_s
            own = np.clip(rng.normal(0.0, spread, len(s)), -reach, reach)
            offsets = own if offsets is None else offsets + own
        segments.append(replace(s, t=t, dt_s=np.maximum(dt, 1e-12), act_offset_s=offsets))
    return replace(data, segments=tuple(segments))
