"""The effect library's contract: names, sim:// keys, units, validation, URL round trip."""

from __future__ import annotations

import importlib

import pytest

from servobench.errors import DriveConfigError, UsageError
from servobench.sim_backend.physics import effects
from servobench.sim_backend.physics.effects.spec import EffectSpec, Screening
from servobench.sim_backend.simurl import DEVICE_KEYS, PLANT_KEYS, plant_from_url, plant_query

LIBRARY = (
    "stribeck",
    "viscous_asymmetry",
    "offset",
    "time_delay",
    "resonance",
    "cogging",
    "saturation",
    "backlash",
    "deadzone",
    "quantization",
    "position_friction",
)


def test_library_names_are_the_contract():
    assert set(effects.names()) == set(LIBRARY)


@pytest.mark.parametrize("name", LIBRARY)
def test_every_module_declares_spec_term_and_screening(name):
    mod = importlib.import_module(effects.EFFECT_MODULES[name])
    assert isinstance(mod.EFFECT, EffectSpec) and mod.EFFECT.name == name
    assert callable(mod.contribute) and callable(mod.screen)
    assert mod.EFFECT.signature and mod.EFFECT.fit and mod.__doc__
    for p in mod.EFFECT.params:
        assert p.unit and p.doc and p.key


def test_keys_are_unique_and_do_not_shadow_plant_or_device_keys():
    keys = [p.key for n in LIBRARY for p in effects.spec(n).params]
    assert len(keys) == len(set(keys))
    assert not set(keys) & (PLANT_KEYS | DEVICE_KEYS)
    assert effects.query_keys() == frozenset(keys)


def test_query_groups_keys_and_fills_defaults():
    got = effects.effects_from_query({"res_wn": 200.0, "stribeck_vs": 0.05, "stribeck_fs": 0.8})
    assert list(got) == ["stribeck", "resonance"]  # library order
    assert got["stribeck"] == {"fs": 0.8, "vs": 0.05}
    assert got["resonance"] == {"wn": 200.0, "zeta": 0.1, "ratio": 0.5}


@pytest.mark.parametrize(
    "query, message",
    [
        ({"stribeck_fs": 0.8}, "needs stribeck_vs"),
        ({"stribeck_fs": 0.8, "stribeck_vs": 0.0}, "out of range"),
        ({"sat": -1.0}, "out of range"),
        ({"res_wn": 100.0, "res_ratio": 1.5}, "out of range"),
        ({"wobble": 1.0}, "unknown effect keys: wobble"),
    ],
)
def test_bad_effect_values_are_usage_errors(query, message):
    with pytest.raises(UsageError, match=message):
        effects.effects_from_query(query)


def test_sim_url_carries_effects_and_rejects_bad_ones_as_config_errors():
    p = plant_from_url("sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4&stribeck_fs=0.8&stribeck_vs=0.05")
    assert p.effects == {"stribeck": {"fs": 0.8, "vs": 0.05}}
    with pytest.raises(DriveConfigError, match="stribeck"):
        plant_from_url("sim://?stribeck_fs=0.8")
    with pytest.raises(DriveConfigError, match="not a number"):
        plant_from_url("sim://?delay=soon")


def test_url_keys_fc_pos_fc_neg_set_the_coulomb_levels_and_stay_the_contract():
    p = plant_from_url("sim://?M=0.2&B=2&fc_pos=0.3&fc_neg=0.6&brk_pos=0.7&delay=0.004")
    assert (p.M, p.B, p.coulomb_pos, p.coulomb_neg, p.brk_pos, p.brk_neg) == (
        0.2,
        2.0,
        0.3,
        0.6,
        0.7,
        None,
    )
    query = plant_query(p)
    assert query["fc_pos"] == 0.3 and query["fc_neg"] == 0.6 and "coulomb_pos" not in query
    assert "brk_neg" not in query and query["delay"] == 0.004
    assert plant_from_url("sim://?" + "&".join(f"{k}={v!r}" for k, v in query.items())) == p
    with pytest.raises(DriveConfigError, match="unknown sim plant key.*coulomb_pos"):
        plant_from_url("sim://?coulomb_pos=0.3")


def test_to_query_inverts_effects_from_query():
    query = {"cog_amp": 0.2, "cog_period": 0.1, "cog_phase": 0.3, "delay": 0.004}
    assert effects.to_query(effects.effects_from_query(query)) == query


def test_cross_checks_against_the_base_plant_happen_when_the_model_is_built():
    from servobench.sim_backend.physics.plant import Plant

    with pytest.raises(UsageError, match="at least the Coulomb"):
        Plant(plant_from_url("sim://?fc_pos=0.5&stribeck_fs=0.3&stribeck_vs=0.1"))
    with pytest.raises(UsageError, match="below B"):
        Plant(plant_from_url("sim://?B=1&visc_asym=1.2"))
    with pytest.raises(UsageError, match="cannot be combined"):
        Plant(plant_from_url("sim://?res_wn=100&backlash=0.01"))


def test_screening_result_is_frozen():
    s = Screening(0.1, {"a": 1.0}, {"a": (0.0, 2.0)}, "found it")
    with pytest.raises(AttributeError):
        s.score = 0.5  # type: ignore[misc]


def test_position_friction_travels_through_its_sim_url_keys():
    url = (
        "sim://?fc_pos=0.5&fc_neg=0.4&posfric_from=0&posfric_to=2&posfric_knots=3"
        "&posfric_0=0&posfric_1=0.2&posfric_2=0.5"
    )
    p = plant_from_url(url).effects["position_friction"]
    assert (p["x_from"], p["x_to"], p["knots"]) == (0.0, 2.0, 3.0)
    assert [p[f"f{i}"] for i in range(8)] == [0.0, 0.2, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0]
    query = effects.to_query({"position_friction": p})
    assert effects.effects_from_query(query) == {"position_friction": p}
    with pytest.raises(UsageError, match="posfric_4 is set but posfric_knots = 3"):
        from servobench.sim_backend.physics.plant import Plant

        Plant(plant_from_url(url + "&posfric_4=0.1"))


def test_optional_functions_come_from_the_module_or_the_registry_s_declared_defaults():
    from servobench.sim_backend.physics.effects import position_friction, stribeck

    base = {"M": 0.1, "B": 1.0, "coulomb_pos": 0.5, "coulomb_neg": 0.4}
    # stribeck defines project: a static level below the Coulomb level is raised to it.
    low = {"fs": 0.1, "vs": 0.05}
    assert effects.project("stribeck", low, base) == stribeck.project(low, base)
    assert effects.project("stribeck", low, base)["fs"] >= 0.5
    # cogging defines none of the three: parameters unchanged, one order, nothing to check.
    cog = {"amp": 0.2, "period": 0.01, "phase": 0.0}
    assert effects.project("cogging", cog, base) == cog
    assert effects.order("cogging", cog) == 0
    assert effects.check("cogging", cog, plant_from_url("sim://")) is None
    # position_friction defines order: its knot count.
    p = plant_from_url("sim://?posfric_from=0&posfric_to=2&posfric_knots=3&posfric_1=0.2").effects[
        "position_friction"
    ]
    assert effects.order("position_friction", p) == position_friction.order(p) == 3
    assert set(effects.OPTIONAL) == {"check", "project", "order"}
