"""Registry of physical effects the simulated drive can add to the base plant.

Each effect lives in its own module and declares its ``sim://`` query keys.
This registry maps query keys to effects and builds the simulation model.
"""

from __future__ import annotations

from collections.abc import Mapping

from drivers.errors import UsageError

#: Effect name -> module that implements it (filled as effects are added).
EFFECT_MODULES: dict[str, str] = {}


def query_keys() -> frozenset[str]:
    """All ``sim://`` query keys that belong to effects."""
    return frozenset()


def effects_from_query(query: Mapping[str, float]) -> dict[str, dict[str, float]]:
    """Group effect query keys into ``{effect name: {parameter: value}}``."""
    if query:
        raise UsageError(f"unknown effect keys: {', '.join(sorted(query))}")
    return {}


def build_model(params):
    """The simulation model for a plant with effects."""
    raise UsageError(f"effects not supported: {', '.join(params.effects)}")
