"""The commissioning configuration, ``bench.toml``.

Every table and key is optional except where a step needs it (``[limits]``
under ``--yes``); unknown tables or keys are an error, never ignored, so a
misspelled limit cannot pass silently. See ``examples/bench.toml`` for the
documented layout::

    [identity]      site, machine, axis, operator (text, for the commissioning record)
    [limits]        max_u, max_v, xmin, xmax      (drive units; +-inf for unlimited travel)
    [bump]          fractions, pulse_s, rest_s, fs_hz, max_speed_fraction, position_tolerance
    [sidbe]         the SIDBE procedure's options (:data:`SIDBE_KEYS`), among them
                    loop = "auto" | "open" | "closed" (auto: closed loop on finite travel)
    [diagnose]      horizon_s
    [design]        phase_margin_deg, delay_cycles, pi_zero_ratio, max_bandwidth_hz, fs_hz
    [compensation]  ref_amplitude, ref_frequency_hz, periods, sign_band
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from servobench.errors import UsageError
from servobench.tomlfile import SENTENCE, TomlTable, read_toml

#: The four limit keys, as in the drive URL query.
LIMIT_KEYS = ("max_u", "max_v", "xmin", "xmax")
#: The keys of ``[sidbe]`` -- the options of the SIDBE procedure commissioning passes
#: on (``SidbeOptions`` fields) -- and the TOML type of each (values are checked there).
SIDBE_KEYS: Mapping[str, type] = {
    "amplitude": float, "ratio": float, "fs_hz": float, "periods": int, "period_s": float,
    "freqs_hz": list, "loop": str, "method": str, "fit_threshold": float,
    "max_iterations": int, "growth": float, "max_amplitude": float, "settle_s": float,
    "resonance": bool,
}  # fmt: skip
#: The keys of ``[diagnose]`` and their types.
DIAGNOSE_KEYS: Mapping[str, type] = {"horizon_s": float}
#: ``bench.toml``'s wording, with an option table's unknown keys said as
#: ``bench.toml [sidbe] has unknown key(s) amplitud`` (the words users know).
_OPTIONS = replace(SENTENCE, unknown="{where} has unknown {noun}(s) {keys} (known: {known})")


@dataclass(frozen=True)
class IdentitySettings:
    """What the commissioning record names besides the drive: where, which axis, who.

    Attributes
    ----------
    site : str
        The plant or workshop (``"Hall 3, line 2"``).
    machine : str
        The machine the axis belongs to (``"press 7"``).
    axis : str
        The axis on that machine (``"X"``, ``"spindle"``).
    operator : str
        Who commissioned it.

    Every field is optional text; ``""`` where not given (the record then says so).
    """

    site: str = ""
    machine: str = ""
    axis: str = ""
    operator: str = ""

    def as_dict(self) -> dict[str, str]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


@dataclass(frozen=True)
class LimitSettings:
    """Limits as written in the configuration; ``None`` where absent.

    Attributes
    ----------
    max_u : float or None
        Largest ``|command|`` [command units] (torque/current).
    max_v : float or None
        Largest ``|velocity|`` [velocity units/s].
    xmin, xmax : float or None
        Allowed travel [position units]; ``-inf``/``inf`` for unlimited (rotary) travel.
    """

    max_u: float | None = None
    max_v: float | None = None
    xmin: float | None = None
    xmax: float | None = None

    def missing(self) -> list[str]:
        """Names of the limits not given."""
        return [k for k in LIMIT_KEYS if getattr(self, k) is None]


@dataclass(frozen=True)
class BumpSettings:
    """The bump test.

    Attributes
    ----------
    fractions : tuple of float
        Pulse amplitudes tried in turn until the axis moves [fraction of max_u], each in (0, 0.5].
    pulse_s : float
        Length of one pulse [s].
    rest_s : float
        Longest zero-command wait after a pulse for the axis to come to rest [s].
    fs_hz : float or None
        Cycle rate of the bump test [Hz]; default (None) the rate the drive's
        link carries, as ``sidbe`` picks it (:meth:`servobench.drivers.base.Drive.max_rate_hz`).
    max_speed_fraction : float
        A pulse ends early when ``|v|`` exceeds this fraction of max_v.
    position_tolerance : float
        Largest relative mismatch between the position change and the integrated velocity.
    """

    fractions: tuple[float, ...] = (0.05, 0.1, 0.2, 0.3)
    pulse_s: float = 0.1
    rest_s: float = 2.0
    fs_hz: float | None = None
    max_speed_fraction: float = 0.5
    position_tolerance: float = 0.25

    def __post_init__(self) -> None:
        if not self.fractions or not all(0 < f <= 0.5 for f in self.fractions):
            raise UsageError("[bump] fractions must be a non-empty list of values in (0, 0.5]")
        for name in ("pulse_s", "rest_s", "fs_hz", "max_speed_fraction", "position_tolerance"):
            if name == "fs_hz" and self.fs_hz is None:
                continue
            if not getattr(self, name) > 0:
                raise UsageError(f"[bump] {name} must be > 0")


@dataclass(frozen=True)
class DesignSettings:
    """Velocity-loop PI design.

    Attributes
    ----------
    phase_margin_deg : float
        Target phase margin [deg], in (20, 85).
    delay_cycles : float or None
        Host/drive delay beyond the zero-order hold [cycles]; 1 for a lock-step
        exchange (the command computed from ``v_k`` acts from ``t_{k+1}``). None
        (the default): from the model, one cycle plus the drive's identified
        action delay (:func:`~servobench.bench.model.program.loop_delay_cycles`).
    pi_zero_ratio : float
        Crossover over PI zero frequency, ``wc * Ti`` (>= 1; 4 costs ~14 deg of phase).
    max_bandwidth_hz : float or None
        Upper bound on the crossover frequency [Hz] (noise, resonances); none by default.
    fs_hz : float or None
        Loop sample rate [Hz]; default: the identification rate.
    """

    phase_margin_deg: float = 60.0
    delay_cycles: float | None = None
    pi_zero_ratio: float = 4.0
    max_bandwidth_hz: float | None = None
    fs_hz: float | None = None

    def __post_init__(self) -> None:
        if not 20.0 < self.phase_margin_deg < 85.0:
            raise UsageError("[design] phase_margin_deg must be in (20, 85)")
        if self.delay_cycles is not None and not self.delay_cycles >= 0:
            raise UsageError("[design] delay_cycles must be >= 0")
        if not self.pi_zero_ratio >= 1:
            raise UsageError("[design] pi_zero_ratio must be >= 1")
        for name in ("max_bandwidth_hz", "fs_hz"):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise UsageError(f"[design] {name} must be > 0")


@dataclass(frozen=True)
class CompensationSettings:
    """The low-speed reversing reference that checks the friction compensation.

    Attributes
    ----------
    ref_amplitude : float or None
        Velocity amplitude [velocity units/s]; default: twice the Coulomb
        breakaway velocity ``mean(Fc)/B``, at most a quarter of max_v.
    ref_frequency_hz : float
        Reversal rate of the sinusoidal reference [Hz].
    periods : float
        Periods simulated.
    sign_band : float
        Reference speed below which the Coulomb feed-forward fades linearly to
        zero [fraction of ref_amplitude].
    """

    ref_amplitude: float | None = None
    ref_frequency_hz: float = 1.0
    periods: float = 2.0
    sign_band: float = 0.02

    def __post_init__(self) -> None:
        if self.ref_amplitude is not None and not self.ref_amplitude > 0:
            raise UsageError("[compensation] ref_amplitude must be > 0")
        for name in ("ref_frequency_hz", "periods"):
            if not getattr(self, name) > 0:
                raise UsageError(f"[compensation] {name} must be > 0")
        if not 0 <= self.sign_band < 1:
            raise UsageError("[compensation] sign_band must be in [0, 1)")


@dataclass(frozen=True)
class CommissionConfig:
    """The whole configuration; ``source`` names the file ("" for defaults)."""

    identity: IdentitySettings = field(default_factory=IdentitySettings)
    limits: LimitSettings = field(default_factory=LimitSettings)
    bump: BumpSettings = field(default_factory=BumpSettings)
    design: DesignSettings = field(default_factory=DesignSettings)
    compensation: CompensationSettings = field(default_factory=CompensationSettings)
    sidbe: Mapping[str, Any] = field(default_factory=dict)
    diagnose: Mapping[str, Any] = field(default_factory=dict)
    source: str = ""


_SECTIONS = {
    "identity": IdentitySettings,
    "limits": LimitSettings,
    "bump": BumpSettings,
    "design": DesignSettings,
    "compensation": CompensationSettings,
}
_OPTION_TABLES = {"sidbe": SIDBE_KEYS, "diagnose": DIAGNOSE_KEYS}


def _section(table: TomlTable, cls: type) -> object:
    """The settings ``cls`` from ``table``: numbers (``fractions``: a list of them; the
    identity: text), all optional."""
    names = [f.name for f in fields(cls)]
    table.allow(names)
    values: dict[str, object] = {}
    for name in names:
        if name not in table:
            continue  # the dataclass default
        if cls is IdentitySettings:
            values[name] = table.get(name, str).strip()
        elif name == "fractions":
            values[name] = tuple(float(v) for v in table.sequence(name, float))
        else:
            values[name] = table.number(name, allow_inf=name in ("xmin", "xmax"))
    try:
        return cls(**values)
    except UsageError as err:
        raise UsageError(f"{table.file}: {err}") from None


def _options(table: TomlTable, keys: Mapping[str, type]) -> dict[str, Any]:
    """An option table (``[sidbe]``, ``[diagnose]``): known keys, each of its type.

    Numbers are finite; ``freqs_hz`` is a list of numbers. The values' ranges are
    the procedure's to check.
    """
    table = TomlTable(table.data, table.file, table.name, wording=_OPTIONS, error=UsageError)
    values: dict[str, Any] = {}
    for name in table.allow(keys):
        kind = keys[name]
        if kind is float:
            values[name] = table.number(name)
        elif kind is list:
            values[name] = tuple(float(f) for f in table.sequence(name, float))
        else:
            values[name] = table.get(name, kind)
    return values


def parse_config(data: Mapping[str, object], source: str = "bench.toml") -> CommissionConfig:
    """Build a :class:`CommissionConfig` from a parsed TOML document."""
    top = TomlTable(data, source, wording=SENTENCE, error=UsageError)
    top.allow([*_SECTIONS, *_OPTION_TABLES], noun="table")
    parts: dict[str, object] = {
        name: _section(top.table(name), cls) for name, cls in _SECTIONS.items() if name in top
    }
    for name, keys in _OPTION_TABLES.items():
        if name in top:
            parts[name] = _options(top.table(name), keys)
    return CommissionConfig(**parts, source=source)  # type: ignore[arg-type]


def load_config(path: str | Path | None) -> CommissionConfig:
    """Read ``bench.toml``; ``None`` gives the defaults (no limits)."""
    if path is None:
        return CommissionConfig()
    return parse_config(read_toml(path, "config", UsageError), source=str(path))
