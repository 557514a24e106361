"""The values to program into the drive, in the log's units and in the drive's own (pure).

Commissioning ends with numbers a technician types into the drive: the
friction feed-forward per direction, the viscous feed-forward, the velocity
PI and any filter. They are computed in the units of the log (SI where the
driver converts, ``unit_u``/``unit_v``/``unit_x``), but a drive takes them in
its own units. A driver that converts states its factors in the log header::

    # scale_u = 0.00064             log unit of u per drive unit (SI per LSB of the command object)
    # scale_u_source = 0x6076 rated torque 640 mN m, per mille
    # scale_v = 0.104719755         likewise for the velocity
    # scale_x = 4.79368996e-05      likewise for the position

A value of dimension ``u^a v^b`` (times seconds) is then
``value_drive = value / (scale_u^a scale_v^b)``. Without these lines the
drive takes the log's units as they are, and both columns agree.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

from servobench.bench.commission.design import (
    FrictionFeedForward,
    PIDesign,
    design_pi,
    friction_feed_forward,
)
from servobench.bench.model.servo import ServoModel
from servobench.errors import LogFormatError
from servobench.units import SignalUnits

#: Log metadata key of each signal's scale factor (log unit per drive unit).
SCALE_KEYS = {"u": "scale_u", "v": "scale_v", "x": "scale_x"}
#: How the drive's own unit of each signal is called where the drive names none.
DRIVE_UNIT = {"u": "drive u unit", "v": "drive v unit", "x": "drive x unit"}


@dataclass(frozen=True)
class DriveScale:
    """Factors from the drive's own numbers to the log's: ``log value = drive value * scale``.

    Attributes
    ----------
    scale : mapping
        ``{"u": .., "v": .., "x": ..}`` [log unit per drive unit]; 1 where not reported.
    sources : mapping
        Where the driver says each factor came from (``scale_u_source`` ...).
    reported : bool
        True when the log carries the drive's scale factors.
    """

    scale: Mapping[str, float] = field(default_factory=lambda: {"u": 1.0, "v": 1.0, "x": 1.0})
    sources: Mapping[str, str] = field(default_factory=dict)
    reported: bool = False

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, str], where: str = "the log") -> DriveScale:
        """The factors a log header states (``scale_u``, ``scale_v``, ``scale_x`` and their sources).

        Raises
        ------
        LogFormatError
            A factor that is not a finite non-zero number.
        """
        scale, sources = {"u": 1.0, "v": 1.0, "x": 1.0}, {}
        reported = False
        for signal, key in SCALE_KEYS.items():
            if key not in metadata:
                continue
            try:
                value = float(metadata[key])
            except ValueError:
                value = math.nan
            if not (math.isfinite(value) and value != 0):
                raise LogFormatError(
                    f"{where}: metadata {key} = {metadata[key]!r} must be a finite non-zero number "
                    "(log units per drive unit)"
                )
            scale[signal], reported = value, True
            sources[signal] = str(metadata.get(f"{key}_source", "")).strip()
        return cls(scale, sources, reported)

    def as_json(self) -> dict[str, object]:
        """``drive_scale`` of a model file: ``{"u": .., "v": .., "x": .., "sources": {..}}``."""
        return {**{s: float(self.scale[s]) for s in "uvx"}, "sources": dict(self.sources)}

    @classmethod
    def from_json(cls, doc: Mapping[str, object], where: str = "model") -> DriveScale:
        """The factors a model file's ``drive_scale`` object states (:meth:`as_json`)."""
        sources = doc.get("sources", {})
        meta = {SCALE_KEYS[s]: str(doc[s]) for s in "uvx" if s in doc and s in (sources or {})}
        meta.update({f"{SCALE_KEYS[s]}_source": str(v) for s, v in (sources or {}).items() if s in SCALE_KEYS})
        return cls.from_metadata(meta, f"{where}: drive_scale")

    def units(self, log_units: SignalUnits) -> SignalUnits:
        """The drive's own units: generic names where it reports factors, else the log's units."""
        if not self.reported:
            return log_units
        return SignalUnits(*(DRIVE_UNIT[s] if s in self.sources else getattr(log_units, s) for s in "uvx"))

    def definitions(self, log_units: SignalUnits) -> list[str]:
        """One sentence per reported factor: ``1 drive u unit = 0.00064 N m (source)``."""
        out = []
        for signal in "uvx":
            if signal in self.sources:
                why = f" ({self.sources[signal]})" if self.sources[signal] else ""
                out.append(f"1 {DRIVE_UNIT[signal]} = {self.scale[signal]:.6g} {log_units.of(signal)}{why}")
        return out


def drive_scale_json(metadata: Mapping[str, str], where: str = "the log") -> dict[str, object]:
    """``drive_scale`` of a model file from a log's header (``{}`` when it states no factors)."""
    scale = DriveScale.from_metadata(metadata, where)
    return scale.as_json() if scale.reported else {}


@dataclass(frozen=True)
class ProgramValue:
    """One value to program.

    Attributes
    ----------
    name : str
        What it is, as a drive's manual would call it.
    value : float
        In the log's units (NaN for a text-only row).
    unit : str
        The log's unit of ``value``.
    drive_value : float
        In the drive's own units.
    drive_unit : str
        The drive's unit of ``drive_value``.
    note : str
        How to use it; for a text-only row, the whole content.
    """

    name: str
    value: float
    unit: str
    drive_value: float
    drive_unit: str
    note: str = ""

    def as_dict(self) -> dict[str, object]:
        return dict(self.__dict__)


def integral_unit(units: SignalUnits) -> str:
    """Unit of ``Ki`` (command per velocity per second): ``N m/rad`` when ``v`` is ``x`` per second."""
    u, v, x = units.of("u"), units.of("v"), units.of("x")
    if units.x and v == f"{x}/s":
        return f"{u}/{x}" if " " not in x else f"{u}/({x})"
    return f"({units.parameters()['B']})/s"


def program_values(
    model: ServoModel,
    ff: FrictionFeedForward,
    pi: PIDesign,
    units: SignalUnits,
    scale: DriveScale = DriveScale(),
) -> tuple[ProgramValue, ...]:
    """The feed-forward, PI and filter values, each in the log's and the drive's units."""
    own = scale.units(units)
    su, sv = scale.scale["u"], scale.scale["v"]
    p, q = units.parameters(), own.parameters()

    def row(name: str, value: float, a: int, b: int, unit: str, drive_unit: str, note: str = ""):
        return ProgramValue(name, value, unit, value / (su**a * sv**b), drive_unit, note)

    gains = "if the drive's velocity loop takes its gains in other units, convert from these"
    rows = [
        row("friction feed-forward, positive motion (Coulomb +)", ff.coulomb_pos, 1, 0, p["u"], q["u"],
            "added for positive reference velocity"),
        row("friction feed-forward, negative motion (Coulomb -)", ff.coulomb_neg, 1, 0, p["u"], q["u"],
            "magnitude, subtracted for negative reference velocity"),
        row("viscous feed-forward (B)", ff.viscous, 1, -1, p["B"], q["B"], "times the reference velocity"),
        row("feed-forward ramp-in band", ff.sign_band, 0, 1, p["v"], q["v"],
            "the Coulomb term ramps in linearly below this reference speed; 0: a step"),
        row("velocity PI: proportional gain Kp", pi.kp, 1, -1, p["B"], q["B"], gains),
        row("velocity PI: integral gain Ki = Kp/Ti", pi.ki, 1, -1, integral_unit(units),
            integral_unit(own), gains),
        row("velocity PI: integral time Ti", pi.ti_s, 0, 0, "s", "s"),
        row("velocity loop sample time", pi.sample_time_s, 0, 0, "s", "s",
            f"designed for {pi.delay_cycles:g} cycle(s) of delay"),
    ]  # fmt: skip
    rows.append(_filter_row(model, pi))
    return tuple(rows)


def loop_delay_cycles(model: ServoModel, fs_hz: float, given: float | None = None) -> float:
    """The delay a velocity loop closed through the exchanges sees [cycles]: ``given`` when
    stated, else one cycle (the command computed from ``v_k`` goes out with the next exchange)
    plus the drive's identified action delay ``model.delay_s`` (from a command's logged instant
    to its action, the sample's lag included) at ``fs_hz`` [Hz]."""
    if given is not None:
        return float(given)
    return 1.0 + model.delay_s * fs_hz


def design_values(
    model: ServoModel,
    units: SignalUnits,
    fs_hz: float,
    scale: DriveScale = DriveScale(),
    *,
    phase_margin_deg: float = 60.0,
    delay_cycles: float | None = None,
    pi_zero_ratio: float = 4.0,
    max_bandwidth_hz: float | None = None,
    sign_band: float = 0.0,
) -> tuple[FrictionFeedForward, PIDesign, tuple[ProgramValue, ...]]:
    """The feed-forward, the velocity PI and the values to program of a saved model, without
    a commissioning: the same design code (:func:`design_pi`, :func:`friction_feed_forward`)
    at the loop rate ``fs_hz`` [Hz], the ramp-in band ``sign_band`` [velocity units/s]; the
    delay from the model unless ``delay_cycles`` is given (:func:`loop_delay_cycles`)."""
    delay_cycles = loop_delay_cycles(model, fs_hz, delay_cycles)
    pi = design_pi(model.M, model.B, fs_hz, phase_margin_deg=phase_margin_deg, delay_cycles=delay_cycles,
                   pi_zero_ratio=pi_zero_ratio, max_bandwidth_hz=max_bandwidth_hz)  # fmt: skip
    ff = friction_feed_forward(model.B, model.coulomb_pos, model.coulomb_neg, sign_band)
    return ff, pi, program_values(model, ff, pi, units, scale)


def _filter_row(model: ServoModel, pi: PIDesign) -> ProgramValue:
    res = model.resonance
    if res is None:
        return ProgramValue(
            "velocity filter", math.nan, "", math.nan, "",
            f"none: no resonance was identified in the excited band; the PI is designed without a "
            f"filter (crossover {pi.crossover_hz:.3g} Hz)",
        )  # fmt: skip
    return ProgramValue(
        "notch filter centre frequency", res.f_hz, "Hz", res.f_hz, "Hz",
        f"at the identified resonance (damping {res.zeta:.3g}); the PI crossover is {pi.crossover_hz:.3g} Hz",
    )  # fmt: skip
