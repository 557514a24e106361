"""Plant parameters from a ``sim://`` URL query or a TOML plant file.

``sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4`` -- the key names are a contract.
``sim://?plant=path/to/plant.toml`` reads the same keys from the file's
``[plant]`` table (keys given in the URL override the file).
``clock=lockstep|real`` chooses the drive's clock mode
(:mod:`servobench.sim_backend.device`), not the physics; so does
``tick=S``, the drive's own control tick [s] (``clock=real`` only; 0, the
default: none; :mod:`servobench.sim_backend.drive_tick`).
"""

from __future__ import annotations

import math
from pathlib import Path

from servobench.drivers.base import COMMON_QUERY_KEYS
from servobench.drivers.url import DriveURL, parse_drive_url
from servobench.errors import DriveConfigError, UsageError
from servobench.sim_backend.physics import effects
from servobench.sim_backend.physics.plant import PlantParams
from servobench.tomlfile import TomlTable, read_toml
from servobench.units import LINEAR, ROTARY, SignalUnits

#: Base physics keys of ``sim://`` and plant files (a contract), each with the
#: :class:`~servobench.sim_backend.physics.coulomb.PlantParams` field it sets. The one place
#: where key and field differ: ``fc_pos``/``fc_neg`` set ``coulomb_pos``/``coulomb_neg``.
PLANT_FIELDS: dict[str, str] = {
    "M": "M",
    "B": "B",
    "fc_pos": "coulomb_pos",
    "fc_neg": "coulomb_neg",
    "brk_pos": "brk_pos",
    "brk_neg": "brk_neg",
    "noise": "noise",
    "noise_x": "noise_x",
    "res_x": "res_x",
    "res_v": "res_v",
}
PLANT_KEYS = frozenset(PLANT_FIELDS)
#: Keys that configure the simulated drive rather than the physics ("pace" is also a common key).
DEVICE_KEYS = frozenset({"seed", "pace", "plant", "units", "clock", "tick", "drift"})
#: ``units=`` of ``sim://``: what the simulated axis's signals are in.
AXIS_UNITS = {"rotary": ROTARY, "linear": LINEAR}


def sim_query_keys() -> frozenset[str]:
    """Every query key ``sim://`` accepts apart from the common drive keys."""
    return PLANT_KEYS | DEVICE_KEYS | effects.query_keys()


def _number(value: object) -> float:
    """``value`` (a number, or its text) as a finite float; ``ValueError`` saying why not."""
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError("is not a number") from None
    if not math.isfinite(out):
        raise ValueError("is not finite")
    return out


def _query_number(key: str, value: object) -> float:
    try:
        return _number(value)
    except ValueError as err:
        raise DriveConfigError(f"sim plant key {key}={value!r} {err}") from None


def load_plant_file(path: str | Path) -> dict[str, float]:
    """The plant keys of a TOML plant file: its ``[plant]`` table, or the whole file if it has none.

    The values are what the URL query takes (numbers, or their text); errors
    name the file, the table and the key.
    """
    top = TomlTable(read_toml(path, "plant file"), f"plant file {path}")
    table = top.table("plant") if "plant" in top else top
    drive_keys = sorted(COMMON_QUERY_KEYS & set(table.data))
    if drive_keys:  # limits and pacing are the drive's, not the plant's: never dropped silently
        raise table.error(drive_keys[0], "is a drive URL key, not a plant key: put it in the URL")
    values = {}
    for key in table.allow(PLANT_KEYS | effects.query_keys()):
        value = table.get(key, object)
        try:
            values[key] = _number(value)
        except ValueError as err:
            raise table.error(key, f"{value!r} {err}") from None
    return values


def plant_from_url(url: DriveURL | str) -> PlantParams:
    """Build :class:`PlantParams` from a ``sim://`` URL (and its plant file, if named)."""
    url = parse_drive_url(url) if isinstance(url, str) else url
    values: dict[str, object] = {}
    if "plant" in url.query:
        values.update(load_plant_file(url.query["plant"]))
    values.update({k: v for k, v in url.query.items() if k not in DEVICE_KEYS})
    for key in COMMON_QUERY_KEYS:
        values.pop(key, None)
    unknown = set(values) - PLANT_KEYS - effects.query_keys()
    if unknown:
        raise DriveConfigError(f"unknown sim plant key(s): {', '.join(sorted(unknown))}")
    base = {PLANT_FIELDS[k]: _query_number(k, values[k]) for k in PLANT_KEYS & set(values)}
    effect_values = {k: _query_number(k, values[k]) for k in set(values) - PLANT_KEYS}
    seed = url.get_int("seed")
    if seed is not None and seed < 0:
        raise DriveConfigError(f"sim seed must be a non-negative integer, got {seed}")
    try:
        return PlantParams(**base, seed=seed, effects=effects.effects_from_query(effect_values))
    except UsageError as err:
        raise DriveConfigError(f"bad sim plant: {err}") from None


def plant_query(params: PlantParams) -> dict[str, float]:
    """The ``sim://`` query of a plant: its base keys (breakaway only when set) and effect keys.

    The inverse of :func:`plant_from_url` for everything but the seed.
    """
    query = {}
    for key, name in PLANT_FIELDS.items():
        value = getattr(params, name)
        if value is not None:
            query[key] = float(value)
    query.update(effects.to_query(params.effects))
    return query


def units_from_url(url: DriveURL) -> SignalUnits:
    """The signal units of a ``sim://`` drive: ``units=rotary`` (N m, rad/s, rad; the
    default) or ``units=linear`` (N, m/s, m)."""
    name = url.get_str("units", "rotary")
    if name not in AXIS_UNITS:
        raise DriveConfigError(f"sim units must be 'rotary' or 'linear', got {name!r}")
    return AXIS_UNITS[name]
