"""``servobench list maps|dialects|effects|keys``: what this build ships, read from its registries.

* ``maps`` -- the shipped Modbus register maps (``map=NAME``), with their units;
* ``dialects`` -- the shipped serial dialects (``dialect=NAME``);
* ``effects`` -- the simulated drive's effects, each with its ``sim://`` keys,
  units (the library's relative unit, and as it reads on a rotary and on a
  linear ``sim://`` axis), ranges and defaults (from the effect modules' own
  declarations);
* ``keys`` -- the URL query keys of every registered scheme (built-in and
  entry points).

Nothing here is a hand-written list: each table is read from the registry
or the declarations the drivers and the simulator use themselves.
"""

from __future__ import annotations

import argparse
import math
from typing import Any

WHAT = ("maps", "dialects", "effects", "keys")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("what", choices=WHAT, help="maps, dialects, effects or keys")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object on stdout")


def run(args: argparse.Namespace) -> int:
    from servobench.bench.report.summary import print_json

    rows = {"maps": maps, "dialects": dialects, "effects": effects, "keys": keys}[args.what]()
    if args.json:
        print_json({args.what: rows})
        return 0
    print({"maps": _print_maps, "dialects": _print_dialects, "effects": _print_effects,
           "keys": _print_keys}[args.what](rows), end="")  # fmt: skip
    return 0


# ------------------------------------------------------------------ the tables
def maps() -> list[dict[str, Any]]:
    """Every shipped register map: name, description, units, source."""
    from servobench.drivers.modbus.regmap import load_map, shipped_maps

    out = []
    for name in shipped_maps():
        m = load_map(name)
        out.append({"name": m.name, "description": m.description, "units": dict(m.signal_units),
                    "fc23": m.fc23, "source": m.source})  # fmt: skip
    return out


def dialects() -> list[dict[str, Any]]:
    """Every shipped serial dialect: name, protocol, firmware, units, reference."""
    from servobench.drivers.serial.dialect import load_dialect, shipped_dialects

    out = []
    for name in shipped_dialects():
        d = load_dialect(name)
        out.append({"name": d.name, "protocol": d.protocol, "firmware": d.firmware,
                    "units": dict(d.units), "reference": d.reference})  # fmt: skip
    return out


def effects() -> list[dict[str, Any]]:
    """Every effect of the simulator with its parameters as the effect module declares them."""
    from servobench.sim_backend.physics import effects as library
    from servobench.sim_backend.simurl import AXIS_UNITS

    out = []
    for name in library.names():
        spec = library.spec(name)
        params = [
            {"key": p.key, "parameter": p.name, "unit": p.unit,
             "units": {axis: su.effect_parameter(p.unit) for axis, su in AXIS_UNITS.items()},
             "range": _range(p), "default": p.default, "meaning": p.doc}  # fmt: skip
            for p in spec.params
        ]
        out.append({"name": name, "summary": spec.summary, "keys": params})
    return out


def keys() -> dict[str, Any]:
    """The query keys of every registered URL scheme; ``common`` are those every scheme takes."""
    from servobench.drivers.base import COMMON_QUERY_KEYS
    from servobench.drivers.registry import available_schemes, resolve
    from servobench.errors import DriveUnavailableError

    schemes: dict[str, Any] = {}
    for scheme in available_schemes():
        try:
            cls = resolve(scheme)
        except DriveUnavailableError as err:
            schemes[scheme] = {"unavailable": str(err)}
            continue
        schemes[scheme] = sorted(set(cls.query_keys) - COMMON_QUERY_KEYS)
    return {"common": sorted(COMMON_QUERY_KEYS), "schemes": schemes}


def _range(p) -> str:
    low = "(" if p.open_lower else "["
    upper = "inf" if math.isinf(p.upper) else f"{p.upper:g}"
    return f"{low}{p.lower:g}, {upper}]"


# ---------------------------------------------------------------- as text
def _units(units: dict[str, str]) -> str:
    return ", ".join(f"{k} [{v}]" for k, v in units.items()) or "units not stated"


def _print_maps(rows: list[dict[str, Any]]) -> str:
    lines = ["Modbus register maps (modbus+tcp:// or modbus+rtu:// ...?map=NAME, or map=FILE.toml):"]
    for r in rows:
        lines += [f"  {r['name']}", f"      {r['description']}", f"      {_units(r['units'])}"]
    return "\n".join(lines) + "\n"


def _print_dialects(rows: list[dict[str, Any]]) -> str:
    lines = ["Serial dialects (serial://PORT?dialect=NAME, or dialect=FILE.toml):"]
    for r in rows:
        lines += [f"  {r['name']}", f"      {r['protocol']}, firmware {r['firmware']}; {_units(r['units'])}",
                  f"      {r['reference']}"]  # fmt: skip
    return "\n".join(lines) + "\n"


def _print_effects(rows: list[dict[str, Any]]) -> str:
    lines = ["Effects of the simulated drive: sim://?KEY=VALUE switches an effect on by any of its keys.",
             "Units: rotary axis (the default) | linear axis (units=linear)."]  # fmt: skip
    for r in rows:
        lines.append(f"  {r['name']}: {r['summary']}")
        for k in r["keys"]:
            default = "required" if k["default"] is None else f"default {k['default']:g}"
            unit = " | ".join(dict.fromkeys(k["units"].values()))
            lines.append(f"      {k['key']:<16} [{unit}] {k['range']}, {default}: {k['meaning']}")
    return "\n".join(lines) + "\n"


def _print_keys(table: dict[str, Any]) -> str:
    lines = [f"Every scheme takes: {', '.join(table['common'])}"]
    for scheme, own in table["schemes"].items():
        if isinstance(own, dict):
            lines.append(f"  {scheme}://  not available: {own['unavailable']}")
        else:
            lines.append(f"  {scheme}://  {', '.join(own) or '(nothing else)'}")
    return "\n".join(lines) + "\n"
