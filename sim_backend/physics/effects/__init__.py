"""Registry of physical effects the simulated drive can add to the base plant.

Each effect lives in its own module (see :mod:`servobench.sim_backend.physics.effects.spec` for
what a module defines) and is listed once in :data:`EFFECT_MODULES`; adding an
effect is one new module plus one line here. Effects are switched on by their
``sim://`` query keys, e.g.
``sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&stribeck_fs=0.8&stribeck_vs=0.05``.

============================  =============================================  ==========================
effect                        keys [units]                                   term
============================  =============================================  ==========================
``stribeck``                  stribeck_fs [u], stribeck_vs [units/s]         friction excess at low speed
``viscous_asymmetry``         visc_asym [u s/unit]                           B +/- dB by direction
``offset``                    offset [u]                                     u + offset
``time_delay``                delay [s]                                      u(t - delay)
``resonance``                 res_wn [rad/s], res_zeta, res_ratio            two-mass series mode
``cogging``                   cog_amp [u], cog_period [unit], cog_phase      amp sin(2 pi x/period + phase)
``saturation``                sat [u]                                        clip(u, -sat, sat)
``backlash``                  backlash [unit], backlash_ratio                play motor -> load
``deadzone``                  deadzone [u]                                   dead band of u
``quantization``              quant [u]                                      quant * round(u / quant)
``position_friction``         posfric_from, posfric_to [unit],               Coulomb + spline g(x)
                              posfric_knots, posfric_0 .. posfric_7 [u]
============================  =============================================  ==========================
"""

from __future__ import annotations

import importlib
from collections.abc import Mapping
from functools import cache
from types import ModuleType

from servobench.errors import UsageError
from servobench.sim_backend.physics.effects.spec import EffectSpec, Terms

#: Effect name -> module that implements it. The order is the library's order.
EFFECT_MODULES: dict[str, str] = {
    "stribeck": "servobench.sim_backend.physics.effects.stribeck",
    "viscous_asymmetry": "servobench.sim_backend.physics.effects.viscous_asymmetry",
    "offset": "servobench.sim_backend.physics.effects.offset",
    "time_delay": "servobench.sim_backend.physics.effects.time_delay",
    "resonance": "servobench.sim_backend.physics.effects.resonance",
    "cogging": "servobench.sim_backend.physics.effects.cogging",
    "saturation": "servobench.sim_backend.physics.effects.saturation",
    "backlash": "servobench.sim_backend.physics.effects.backlash",
    "deadzone": "servobench.sim_backend.physics.effects.deadzone",
    "quantization": "servobench.sim_backend.physics.effects.quantization",
    "position_friction": "servobench.sim_backend.physics.effects.position_friction",
}


@cache
def module(name: str) -> ModuleType:
    """The module implementing effect ``name``."""
    try:
        path = EFFECT_MODULES[name]
    except KeyError:
        raise UsageError(f"unknown effect {name!r} (known: {', '.join(EFFECT_MODULES)})") from None
    return importlib.import_module(path)


def spec(name: str) -> EffectSpec:
    return module(name).EFFECT


def names() -> tuple[str, ...]:
    """Effect names in library order."""
    return tuple(EFFECT_MODULES)


# ------------------------------------------------ the optional functions, with their defaults
def _no_check(p: Mapping[str, float], plant) -> None:
    """Nothing to cross-check against the base plant."""


def _unchanged(p: Mapping[str, float], base: Mapping[str, float]) -> dict[str, float]:
    """Every value in range is physical: the parameters as they are."""
    return dict(p)


def _one_order(p: Mapping[str, float]) -> int:
    """One model order: the parameter sets of a screening differ in values only."""
    return 0


#: The optional functions of an effect module (see :mod:`.spec`) and what an effect that does
#: not define one gets: callers use :func:`check`, :func:`project` and :func:`order`, never the
#: module's attributes, so a module defines only what it needs.
OPTIONAL = {"check": _no_check, "project": _unchanged, "order": _one_order}


def _optional(name: str, which: str):
    return vars(module(name)).get(which, OPTIONAL[which])


def check(name: str, p: Mapping[str, float], plant) -> None:
    """Cross-check effect ``name``'s parameters against the base plant (raises UsageError)."""
    _optional(name, "check")(p, plant)


def project(name: str, p: Mapping[str, float], base: Mapping[str, float]) -> dict[str, float]:
    """Effect ``name``'s parameters made physical against the base model (``M``, ``B``,
    ``coulomb_pos``, ``coulomb_neg``); the diagnosis applies it at every step of a refit."""
    return _optional(name, "project")(p, base)


def order(name: str, p: Mapping[str, float]) -> int:
    """The model order of a parameter set of effect ``name`` (a spline's knot count; 0 for
    effects of one order)."""
    return _optional(name, "order")(p)


@cache
def _key_table() -> dict[str, tuple[str, str]]:
    """``sim://`` key -> (effect, parameter)."""
    table: dict[str, tuple[str, str]] = {}
    for name in EFFECT_MODULES:
        for p in spec(name).params:
            if p.key in table:
                raise RuntimeError(f"effect key {p.key} declared twice")
            table[p.key] = (name, p.name)
    return table


def query_keys() -> frozenset[str]:
    """All ``sim://`` query keys that belong to effects."""
    return frozenset(_key_table())


def effects_from_query(query: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """Group effect query keys into ``{effect name: {parameter: value}}``, validated.

    An effect is switched on by any of its keys; its other keys take their
    defaults, and a required key that is missing is an error.

    Raises
    ------
    UsageError
        Unknown key, value out of range, required key missing.
    """
    table = _key_table()
    unknown = sorted(set(query) - set(table))
    if unknown:
        raise UsageError(f"unknown effect keys: {', '.join(unknown)}")
    grouped: dict[str, dict[str, float]] = {}
    for key, value in query.items():
        name, _ = table[key]
        grouped.setdefault(name, {})[key] = value
    out: dict[str, dict[str, float]] = {}
    for name in EFFECT_MODULES:  # library order, whatever the URL order
        if name in grouped:
            out[name] = validate(name, grouped[name], by_key=True)
    return out


def validate(name: str, values: Mapping[str, float], *, by_key: bool = False) -> dict[str, float]:
    """Parameters of effect ``name`` with defaults filled in and ranges checked.

    ``values`` is keyed by parameter name, or by ``sim://`` key when ``by_key``.
    """
    s = spec(name)
    given = dict(values)
    out: dict[str, float] = {}
    for p in s.params:
        label = p.key if by_key else p.name
        if label in given:
            out[p.name] = p.validate(given.pop(label), name)
        elif p.default is None:
            raise UsageError(f"effect {name} needs {p.key} [{p.unit}] ({p.doc})")
        else:
            out[p.name] = p.default
    if given:
        raise UsageError(f"effect {name} has no parameter(s) {', '.join(sorted(given))}")
    return out


def to_query(effects: Mapping[str, Mapping[str, float]]) -> dict[str, float]:
    """Inverse of :func:`effects_from_query`: ``{sim key: value}``."""
    out: dict[str, float] = {}
    for name, values in effects.items():
        keys = {p.name: p.key for p in spec(name).params}
        for pname, value in values.items():
            out[keys[pname]] = float(value)
    return out


def collect_terms(params) -> Terms:
    """The :class:`Terms` of every effect of a :class:`~servobench.sim_backend.physics.coulomb.PlantParams`."""
    terms = Terms()
    for name, values in params.effects.items():
        values = validate(name, values)
        check(name, values, params)
        module(name).contribute(values, params, terms)
    return terms
