"""Discoverability: ``servobench list``, "did you mean" for URL keys, usage without arguments.

``list`` must agree with what the drivers and the simulator accept: every
key it lists for a scheme opens (or fails on its value, never as unknown),
every effect key it lists switches its effect on in a real ``sim://`` drive,
and every map and dialect it lists loads by name from another folder.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from servobench.drivers.registry import open_drive
from servobench.errors import DriveConfigError


def servobench(*args: str, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "servobench", *args], capture_output=True, text=True, timeout=60, cwd=cwd
    )


def listed(what: str, tmp_path) -> object:
    p = servobench("list", what, "--json", cwd=tmp_path)  # not the checkout: shipped data by name
    assert p.returncode == 0, p.stderr
    return json.loads(p.stdout)[what]


def test_maps_and_dialects_load_by_the_names_listed(tmp_path):
    from servobench.drivers.modbus.regmap import load_map
    from servobench.drivers.serial.dialect import load_dialect

    maps = listed("maps", tmp_path)
    assert {"servobench-sim", "zlac8015d"} <= {m["name"] for m in maps}
    for m in maps:
        assert load_map(m["name"]).signal_units == m["units"]  # the registers' own units, else [units]
    dialects = listed("dialects", tmp_path)
    assert "odrive" in {d["name"] for d in dialects}
    for d in dialects:
        assert load_dialect(d["name"]).protocol == d["protocol"]
    text = servobench("list", "maps", cwd=tmp_path).stdout
    assert "zlac8015d" in text and "ZLAC8015D" in text


def test_every_listed_effect_key_switches_its_effect_on_in_a_sim_drive(tmp_path):
    effects = listed("effects", tmp_path)
    names = [e["name"] for e in effects]
    assert {"stribeck", "cogging", "time_delay"} <= set(names)
    keys = {k["key"] for e in effects for k in e["keys"]}
    assert {"stribeck_fs", "cog_amp", "delay"} <= keys and "stribeck" not in keys
    for e in effects:
        query = {}
        for k in e["keys"]:
            low, high = (float(x) for x in k["range"].strip("[()]").split(","))
            value = k["default"] if k["default"] is not None else min(max(low, 0.0) + 0.5, high)
            query[k["key"]] = value
        if e["name"] == "stribeck":
            query["stribeck_fs"] = 1.0  # at least the Coulomb levels
        if e["name"] == "position_friction":
            query.update(posfric_knots=2, posfric_to=1.5)  # a whole count, beyond posfric_from
        url = "sim://?" + "&".join(f"{key}={v}" for key, v in query.items())
        with open_drive(url) as drive:
            assert e["name"] in drive.device.params.effects, (e["name"], url)


def test_listed_effect_units_are_those_of_the_sim_axis_they_switch_on(tmp_path):
    """An effect parameter in "command units" reads N m on the default (rotary) sim:// axis and
    N with units=linear: the units the simulated drive itself reports for u, v and x."""
    effects = {e["name"]: e for e in listed("effects", tmp_path)}
    by_key = {k["key"]: k for e in effects.values() for k in e["keys"]}
    relative = {"command units": "u", "units/s": "v", "units": "x"}
    for axis in ("rotary", "linear"):
        with open_drive(f"sim://?units={axis}") as drive:
            signal = drive.info().units
        for key, k in by_key.items():
            if k["unit"] in relative:
                assert k["units"][axis] == signal[relative[k["unit"]]], (key, axis)
            elif k["unit"] == "command units*s/unit":
                assert k["units"][axis] == {"rotary": "N m s/rad", "linear": "N s/m"}[axis]
            else:  # absolute units (s, rad of a phase, 1) read the same on both axes
                assert k["units"][axis] == k["unit"], key
    assert by_key["stribeck_fs"]["units"] == {"rotary": "N m", "linear": "N"}
    text = servobench("list", "effects", cwd=tmp_path).stdout
    assert "stribeck_vs      [rad/s | m/s]" in text and "command units" not in text


def test_listed_keys_are_exactly_the_keys_each_scheme_takes(tmp_path):
    table = listed("keys", tmp_path)
    assert {"max_u", "watchdog", "pace"} <= set(table["common"])
    assert set(table["schemes"]) >= {"sim", "canopen", "modbus+tcp", "modbus+rtu", "serial"}
    for scheme, own in table["schemes"].items():
        for key in [*own, *table["common"]]:
            try:
                open_drive(f"{scheme}://x?{key}=0")
            except DriveConfigError as err:
                assert "does not take" not in str(err), (scheme, key, err)
            except Exception:  # a bad value or a missing device: the key itself was taken
                pass
        with pytest.raises(DriveConfigError, match="does not take query key"):
            open_drive(f"{scheme}://x?surely_not_a_key=1")


def test_unknown_url_keys_get_a_did_you_mean():
    with pytest.raises(DriveConfigError, match=r"stribeck.*did you mean stribeck_\w+"):
        open_drive("sim://?stribeck=1")
    with pytest.raises(DriveConfigError, match="did you mean fc_pos"):
        open_drive("sim://?fcpos=0.5")
    with pytest.raises(DriveConfigError) as info:
        open_drive("sim://?zzzzzz=1")
    assert "did you mean" not in str(info.value)


def test_no_arguments_prints_the_usage_with_every_command():
    p = servobench()
    assert p.returncode == 0 and p.stdout.startswith("usage: servobench")
    for command in ("validate", "list", "identify", "diagnose", "sidbe"):
        assert command in p.stdout


def test_json_errors_of_every_json_command(tmp_path):
    """Under --json, any error (even a malformed command line) prints one {"error": ...} object."""
    cases = [
        ["identify", str(tmp_path / "nope.csv")],
        ["diagnose", str(tmp_path / "nope.csv")],
        ["validate", str(tmp_path / "nope.json"), str(tmp_path / "nope.csv")],
        ["sidbe", "--drive", "sim://?bogus=1"],
        ["run", "--drive", "sim://", "--out", str(tmp_path / "l.csv"), "--periods", "1"],
        ["list", "nothing"],
    ]
    for args in cases:
        p = servobench(*args, "--json")
        assert p.returncode in (1, 2), (args, p.stderr)
        err = p.stderr.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("servobench: error: ")
        assert json.loads(p.stdout) == {"error": err[0].removeprefix("servobench: error: ")}, args
