"""The identified servo model and the result of an identification.

Model (command units ``u``, velocity ``v``)::

    M dv/dt + B v = u - F_f,   F_f = +coulomb_pos (v > 0),  -coulomb_neg (v < 0)

with the linear block ``1/(M s + B)``: pole ``-B/M`` [1/s], DC gain ``1/B``
[velocity units per command unit]. ``coulomb_pos`` and ``coulomb_neg`` are
magnitudes (>= 0) in command units. An optional series resonance (the
paper's eq. (2)-(3)) multiplies the linear block by
``wn^2 / (s^2 + 2 zeta wn s + wn^2)``.

This module is public API (``diagnose`` and ``commission`` build on it):
:class:`ServoModel`, :class:`Resonance`, :class:`ModelResponse`,
:class:`IdentificationResult`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from servobench.bench.identify.delay import merged_grid
from servobench.bench.identify.frequency import model_frf
from servobench.errors import IdentificationError, UsageError
from servobench.sim_backend.physics.coulomb import (
    PlantParams,
    PlantState,
    simulate_coulomb,
    simulate_coulomb_steps,
)
from servobench.units import SignalUnits

#: Keys of :attr:`IdentificationResult.std` (the base model's four parameters).
STD_KEYS = ("M", "B", "coulomb_pos", "coulomb_neg")
#: The std key of the drive's action delay (:attr:`ServoModel.delay_s`), present where it was identified.
DELAY_KEY = "delay_s"


@dataclass(frozen=True)
class Resonance:
    """Series resonance ``wn^2 / (s^2 + 2 zeta wn s + wn^2)``: ``wn_rad_s`` [rad/s], ``zeta`` [-]."""

    wn_rad_s: float
    zeta: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.wn_rad_s) and self.wn_rad_s > 0):
            raise IdentificationError(f"resonance frequency must be > 0 rad/s, got {self.wn_rad_s}")
        if not (math.isfinite(self.zeta) and self.zeta > 0):
            raise IdentificationError(f"resonance damping must be > 0, got {self.zeta}")

    @property
    def f_hz(self) -> float:
        return self.wn_rad_s / (2 * math.pi)

    def response(self, s: np.ndarray) -> np.ndarray:
        """Frequency response at Laplace points ``s`` [rad/s]."""
        w2 = self.wn_rad_s**2
        return w2 / (s * s + 2 * self.zeta * self.wn_rad_s * s + w2)

    def filter_velocity(self, v: np.ndarray, dt_s: float) -> np.ndarray:
        """Pass a sampled velocity through the resonance (ZOH-discretised, at rest initially)."""
        from scipy import signal

        num, den = [self.wn_rad_s**2], [1.0, 2 * self.zeta * self.wn_rad_s, self.wn_rad_s**2]
        bd, ad, _ = signal.cont2discrete((num, den), dt_s, method="zoh")
        return signal.lfilter(np.ravel(bd), ad, v)


@dataclass(frozen=True)
class ModelResponse:
    """Simulated response, arrays of shape ``(n,)``: velocity and position at the start of each interval."""

    v: np.ndarray
    x: np.ndarray


@dataclass(frozen=True)
class ServoModel:
    """The identified plant.

    Attributes
    ----------
    M : float
        Inertia/mass [command units * s^2 / position unit], > 0.
    B : float
        Viscous coefficient [command units * s / position unit], > 0.
    coulomb_pos, coulomb_neg : float
        Coulomb friction magnitude in positive / negative motion [command units], >= 0.
    resonance : Resonance or None
        Optional series resonance of the linear block.
    delay_s : float
        The drive's effective action delay [s]: from a command's logged
        instant to the instant it acts on the plant, the sample's lag included
        (a drive that samples at its last control tick and acts at its next
        one: about one tick). ``u[k]`` logged at ``t_k`` acts over
        ``[t_k + delay_s, t_{k+1} + delay_s)``; 0 is the plain zero-order hold.
        Negative where the command is sent ahead of its sample's query and
        acts before the logged instant (``command_lead_s``, the ODrive ASCII
        protocol on a drive without a tick of its own).
    """

    M: float
    B: float
    coulomb_pos: float
    coulomb_neg: float
    resonance: Resonance | None = None
    delay_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("M", "B"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise IdentificationError(
                    f"identified {name} = {value:.4g} is not a finite positive number; "
                    "the data do not fit a damped first-order plant"
                )
        for name in ("coulomb_pos", "coulomb_neg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise IdentificationError(f"identified {name} = {value!r} is not >= 0")
        if not math.isfinite(self.delay_s):
            raise IdentificationError(f"identified delay_s = {self.delay_s!r} is not a finite delay")

    @property
    def pole(self) -> float:
        """Pole of the linear block, ``-B/M`` [1/s]."""
        return -self.B / self.M

    @property
    def dc_gain(self) -> float:
        """DC gain of the linear block, ``1/B`` [velocity units per command unit]."""
        return 1.0 / self.B

    @property
    def time_constant_s(self) -> float:
        """``M/B`` [s]."""
        return self.M / self.B

    def to_plant_params(self, **extra: Any) -> PlantParams:
        """The rigid-body part as :class:`~servobench.sim_backend.physics.coulomb.PlantParams` (the resonance is not carried).

        ``extra`` sets other plant fields (``noise``, ``seed``, ...).
        """
        try:
            return PlantParams(
                M=self.M,
                B=self.B,
                coulomb_pos=self.coulomb_pos,
                coulomb_neg=self.coulomb_neg,
                **extra,
            )
        except UsageError as err:
            raise IdentificationError(f"model cannot be simulated: {err}") from None

    def frequency_response(self, f_hz: np.ndarray, dt_s: float | None = None) -> np.ndarray:
        """Linear-block response at ``f_hz`` [Hz]; with ``dt_s`` the exact ZOH-sampled one."""
        return model_frf(self, np.asarray(f_hz, dtype=float), dt_s)

    def simulate(self, u: np.ndarray, fs_hz: float, v0: float = 0.0) -> ModelResponse:
        """Noise-free response to ``u`` held over each of ``1/fs_hz`` [s] (exact ZOH with stick-slip).

        Parameters
        ----------
        u : ndarray, shape (n,)
            Command [command units].
        fs_hz : float
            Sample rate [Hz].
        v0 : float
            Initial velocity [units/s] (position starts at 0).

        Returns
        -------
        ModelResponse
            ``v[k]``, ``x[k]`` sampled at ``t_k`` before ``u[k]`` acts (at
            ``t_k + delay_s``; the command before ``u[0]`` is 0). With a
            resonance, the rigid-body velocity is passed through it (an
            approximation: friction acts on the rigid-body velocity).
        """
        if not (math.isfinite(fs_hz) and fs_hz > 0):
            raise UsageError(f"sample rate must be > 0 Hz, got {fs_hz}")
        dt = 1.0 / fs_hz
        if self.delay_s != 0:  # u[k] acts from t_k + delay_s: simulated on the switch grid
            u_m, dt_m, rows = merged_grid(np.asarray(u, dtype=float), dt, self.delay_s)
            v, x, _ = simulate_coulomb_steps(u_m, dt_m, self.to_plant_params(), PlantState(v0, 0.0))
            v, x = v[rows], x[rows]
        else:
            v, x, _ = simulate_coulomb(
                np.asarray(u, dtype=float), dt, self.to_plant_params(), PlantState(v0, 0.0)
            )
        if self.resonance is not None:
            v = self.resonance.filter_velocity(v, dt)
            x = np.concatenate(([0.0], np.cumsum(v[:-1]) * dt))
        return ModelResponse(v, x)

    def as_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "M": self.M,
            "B": self.B,
            "pole": self.pole,
            "dc_gain": self.dc_gain,
            "coulomb_pos": self.coulomb_pos,
            "coulomb_neg": self.coulomb_neg,
            "delay_s": self.delay_s,
        }
        if self.resonance is not None:
            out["resonance"] = {"wn_rad_s": self.resonance.wn_rad_s, "zeta": self.resonance.zeta}
        return out


@dataclass(frozen=True)
class IdentificationResult:
    """A model with how it was found and how well it reproduces the data.

    Attributes
    ----------
    model : ServoModel
    method : str
        ``"sidbe"`` or ``"joint"``.
    fit_percent : float
        ``100 * (1 - ||v - v_sim|| / ||v - mean(v)||)`` over all runs, ``v_sim``
        simulated from the logged ``u`` (100 = perfect).
    std : mapping
        1-sigma uncertainties of ``M``, ``B``, ``coulomb_pos``, ``coulomb_neg``.
    selection : str
        One sentence: which method was used and why.
    estimator : str
        The estimator inside the method (e.g. ``"zoh-ls"``, ``"output-error"``, ``"idim-ls"``, ``"frf"``).
    noise_std : float
        Estimated velocity-sensor noise [velocity units] (0 for noise-free data).
    validation : mapping
        Held-out fit [%] per candidate method when ``auto`` compared them.
    notes : tuple of str
        Caveats (derived velocity, fallbacks, ...).
    frf : FrequencyResponse or None
        SIDBE's measured differential FRF (for plots).
    verification : Verification or None
        Measured and simulated velocity per run (for plots).
    units : SignalUnits
        Units of the log's signals; :meth:`to_json` gives every parameter's unit.
    timing : object or None
        The timing figure of a real-time log
        (:class:`~servobench.bench.identify.timing.TimingFigure`); None for
        logs streamed lock-step or written by other tools. :meth:`to_json`
        gives it as ``timing`` and its source as ``clock_source`` (both None without one).
    """

    model: ServoModel
    method: str
    fit_percent: float
    std: Mapping[str, float]
    selection: str = ""
    estimator: str = ""
    noise_std: float = 0.0
    validation: Mapping[str, float] = field(default_factory=dict)
    notes: tuple[str, ...] = ()
    frf: Any = None
    verification: Any = None
    units: SignalUnits = SignalUnits()
    timing: Any = None

    def to_json(self) -> dict[str, Any]:
        """Plain-JSON dict with the contract keys (``M``, ``B``, ``pole``, ``dc_gain``,
        ``coulomb_pos``, ``coulomb_neg``, ``fit_percent``, ``method``, ``std``, ``selection``,
        ``units``: the unit of every parameter and signal, see :mod:`servobench.units`)."""
        out = self.model.as_dict()
        out.update(
            {
                "fit_percent": _finite(self.fit_percent),
                "method": self.method,
                "std": {k: _finite(self.std.get(k, math.nan)) for k in (*STD_KEYS, DELAY_KEY)},
                "selection": self.selection,
                "estimator": self.estimator,
                "noise_std": _finite(self.noise_std),
                "validation": {k: _finite(v) for k, v in self.validation.items()},
                "notes": list(self.notes),
                "units": self.units.parameters(),
                "clock_source": None if self.timing is None else self.timing.clock_source,
                "timing": None if self.timing is None else self.timing.to_json(),
            }
        )
        return out


def _finite(value: float) -> float | None:
    value = float(value)
    return value if math.isfinite(value) else None


def fit_percent(measured: np.ndarray, simulated: np.ndarray) -> float:
    """``100 * (1 - ||v - v_sim|| / ||v - mean(v)||)`` [%]; -inf when ``v`` is constant."""
    measured = np.asarray(measured, dtype=float)
    den = float(np.linalg.norm(measured - measured.mean()))
    if den == 0.0:
        return -math.inf
    return 100.0 * (1.0 - float(np.linalg.norm(measured - np.asarray(simulated))) / den)
