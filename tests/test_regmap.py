"""Register-map codec (golden vectors) and map validation."""

from __future__ import annotations

import copy
import math
from pathlib import Path

import pytest

from servobench.drivers.modbus.regmap import (
    Register,
    decode,
    decode_raw,
    decode_string,
    encode,
    encode_raw,
    encode_string,
    load_map,
    parse_map,
    resolve_map,
    shipped_maps,
    words_of,
)
from servobench.errors import DriveConfigError, UsageError
from servobench.tomlfile import read_toml


def reg(
    fmt: str, scale: float = 1.0, word_order: str = "big", byte_order: str = "big", count: int = 0
) -> Register:
    from servobench.drivers.modbus.regmap import FORMATS

    return Register("r", 0, fmt, count or FORMATS[fmt][1], scale, word_order, byte_order)


# --------------------------------------------------------------- golden vectors
@pytest.mark.parametrize(
    ("fmt", "raw", "word_order", "byte_order", "words"),
    [
        ("int16", -1, "big", "big", [0xFFFF]),
        ("int16", -32768, "big", "big", [0x8000]),
        ("int16", 0x1234, "big", "little", [0x3412]),
        ("uint16", 0xFFFF, "big", "big", [0xFFFF]),
        ("int32", -2, "big", "big", [0xFFFF, 0xFFFE]),
        ("int32", -2, "little", "big", [0xFFFE, 0xFFFF]),
        ("int32", 0x11223344, "big", "big", [0x1122, 0x3344]),
        ("int32", 0x11223344, "little", "big", [0x3344, 0x1122]),
        ("int32", 0x11223344, "big", "little", [0x2211, 0x4433]),
        ("int32", 0x11223344, "little", "little", [0x4433, 0x2211]),
        ("uint32", 0xDEADBEEF, "big", "big", [0xDEAD, 0xBEEF]),
        ("uint32", 0xDEADBEEF, "little", "big", [0xBEEF, 0xDEAD]),
        ("int32", -2147483648, "big", "big", [0x8000, 0x0000]),
        ("float32", 1.0, "big", "big", [0x3F80, 0x0000]),
        ("float32", -2.5, "little", "big", [0x0000, 0xC020]),
    ],
)
def test_raw_golden_vectors_both_ways(fmt, raw, word_order, byte_order, words):
    r = reg(fmt, word_order=word_order, byte_order=byte_order)
    assert encode_raw(r, raw) == words
    assert decode_raw(r, words) == raw


@pytest.mark.parametrize(
    ("fmt", "words", "value"),
    [
        ("int16", [0x8000], -32768),
        ("uint16", [0x8000], 32768),
        ("int32", [0xFFFF, 0xFFFF], -1),
        ("uint32", [0xFFFF, 0xFFFF], 4294967295),
    ],
)
def test_signedness(fmt, words, value):
    assert decode_raw(reg(fmt), words) == value


def test_scaling_golden_vectors():
    micro = reg("int32", scale=1e-6)
    assert encode(micro, 1.234567) == [0x0012, 0xD687]  # 1234567
    assert encode(micro, -1.234567) == [0xFFED, 0x2979]  # -1234567
    assert decode(micro, [0xFFED, 0x2979]) == pytest.approx(-1.234567, abs=1e-12)
    milli = reg("int16", scale=0.001)
    assert encode(milli, 0.5) == [500]
    assert encode(milli, -0.0004) == [0]  # rounds to the nearest count
    assert encode(milli, 0.0016) == [2]
    rpm = reg("int16", scale=0.1 / 60)
    assert decode(rpm, [600]) == pytest.approx(1.0)  # 60.0 r/min = 1 rev/s
    assert encode(reg("float32", scale=2.0), 3.0) == [0x3FC0, 0x0000]  # raw 1.5


def test_string_codec():
    r = reg("string", count=4)
    assert encode_string(r, "servo") == [0x7365, 0x7276, 0x6F00, 0x0000]
    assert decode_string(r, [0x7365, 0x7276, 0x6F00, 0x0000]) == "servo"
    with pytest.raises(UsageError, match="longer"):
        encode_string(r, "much too long")


@pytest.mark.parametrize(
    ("r", "value"),
    [
        (reg("int16"), 32768),
        (reg("uint16"), -1),
        (reg("int16", 0.001), 40.0),
        (reg("int32"), math.nan),
        (reg("float32"), math.inf),
        (reg("float32"), 1e40),
    ],
)
def test_out_of_range_values_are_rejected(r, value):
    with pytest.raises(UsageError, match="'r'"):
        encode(r, value)


def test_decode_checks_word_count_and_width():
    with pytest.raises(UsageError, match="2 word"):
        decode(reg("int32"), [1])
    with pytest.raises(UsageError, match="16-bit"):
        decode(reg("int16"), [0x10000])


def test_words_of_block():
    m = load_map("servobench-sim")
    block = m.feedback
    words = list(range(100, 100 + block.count))
    pos = m["position"]
    assert words_of(block, pos, words) == words[pos.address - block.address :][:2]


# ------------------------------------------------------------------ shipped maps
def test_shipped_maps_load():
    assert {"servobench-sim", "zlac8015d"} <= set(shipped_maps())
    sim = load_map("servobench-sim")
    assert sim.fc23 and sim.feedback.names == (
        "status",
        "fault",
        "timestamp",
        "velocity",
        "position",
    )
    assert sim.feedback.count == 8
    z = load_map("zlac8015d")
    assert not z.fc23
    assert (z.feedback.address, z.feedback.count) == (0x20A5, 7)
    assert z.source and z.setup[0].address == 0x200D


def test_map_by_path(tmp_path: Path):
    path = tmp_path / "mine.toml"
    path.write_text(
        Path(resolve_map("servobench-sim")).read_text().replace('"servobench-sim"', '"mine"')
    )
    assert load_map(str(path)).name == "mine"


def test_unknown_map_name_lists_shipped():
    with pytest.raises(DriveConfigError, match="servobench-sim"):
        load_map("no-such-drive")
    with pytest.raises(DriveConfigError, match="does not exist"):
        load_map("/nonexistent/x.toml")


def test_toml_syntax_error_names_file(tmp_path: Path):
    path = tmp_path / "broken.toml"
    path.write_text("[map\nname = 1\n")
    with pytest.raises(DriveConfigError, match="broken.toml"):
        load_map(str(path))


# -------------------------------------------------------------------- validation
SIM_DOC = read_toml(resolve_map("servobench-sim"), "register map file")


def _set(doc, dotted, value):
    *parents, last = dotted.split(".")
    node = doc
    for p in parents:
        node = node.setdefault(p, {})  # [units] is optional: the shipped map gives register units
    if value is _DELETE:
        del node[last]
    else:
        node[last] = value


_DELETE = object()


@pytest.mark.parametrize(
    ("dotted", "value", "expect"),
    [
        ("registers.velocity", _DELETE, r"\[registers\] velocity: is required"),
        (
            "registers.velocity.format",
            "int33",
            r"\[registers.velocity\] format: 'int33' is not one of",
        ),
        ("registers.velocity.address", 70000, r"\[registers.velocity\] address: 70000 is outside"),
        (
            "registers.velocity.address",
            True,
            r"\[registers.velocity\] address: expected int, got True",
        ),
        ("registers.velocity.adress", 3, r"\[registers.velocity\] adress: unknown key"),
        ("registers.velocty", {"address": 3}, r"\[registers\] velocty: unknown register"),
        ("registers.velocity.scale", 0, r"\[registers.velocity\] scale: 0 must be"),
        ("registers.velocity.word_order", "middle", r"\[registers.velocity\] word_order: 'middle'"),
        ("registers.velocity.access", "w", r"\[registers.velocity\] access: the host reads"),
        (
            "registers.position.address",
            0x0025,
            r"\[registers\] position: overlaps register 'velocity'",
        ),
        ("registers.command.type", "input", r"\[registers.command\] access: the host writes"),
        ("registers.command.access", "r", r"\[registers.command\] access: the host writes"),
        ("registers.vendor.count", 0, r"\[registers.vendor\] count: 0 is outside"),
        (
            "registers.vendor.scale",
            2.0,
            r"\[registers.vendor\] scale: a string register takes no scale",
        ),
        (
            "registers.product",
            {"address": 0x108, "format": "float32"},
            r"\[registers.product\] format: identity registers",
        ),
        ("control.enable", [], r"\[control\] enable: must not be empty"),
        ("control.enable", [70000], r"\[control\] enable: .* 16-bit"),
        ("control.disable", _DELETE, r"\[control\] disable: is required"),
        ("watchdog.feed", "register", r"\[watchdog\] feed: 'register' needs"),
        ("watchdog.feed", "sometimes", r"\[watchdog\] feed: 'sometimes' is not one of"),
        ("map.fc23", "yes", r"\[map\] fc23: expected bool, got 'yes'"),
        ("map.name", _DELETE, r"\[map\] name: is required"),
        ("map.colour", "red", r"\[map\] colour: unknown key"),
        ("status.fault_mask", "8", r"\[status\] fault_mask: expected int, got '8'"),
        (
            "setup",
            [{"address": 1, "value": -1}],
            r"\[setup\[0\]\] value: address and value must be",
        ),
        ("units.t", "s", r"\[units\] t: unknown key"),
        ("extra", {}, r"\[top level\] extra: unknown key"),
        # units, fc23 = "auto" and turnaround_ms
        ("registers.vendor.unit", "V", r"\[registers.vendor\] unit: only scaled values take a unit"),
        ("registers.control.unit", "1", r"\[registers.control\] unit: only scaled values"),
        ("registers.cycle.unit", "ms", r"\[registers.cycle\] unit: 'ms': the host reads and writes"),
        ("units.v", "rpm", r"\[units\] v: 'rpm' contradicts \[registers.velocity\] unit 'rad/s'"),
        ("map.turnaround_ms", -1.0, r"\[map\] turnaround_ms: -1.0 must be >= 0"),
        ("map.fc23", "sometimes", r"\[map\] fc23: expected bool, got 'sometimes' \(or 'auto'\)"),
    ],
)
def test_malformed_entries_name_file_and_key(dotted, value, expect):
    doc = copy.deepcopy(SIM_DOC)
    _set(doc, dotted, value)
    with pytest.raises(DriveConfigError, match=r"^my-map\.toml: " + expect):
        parse_map(doc, "my-map.toml")


def test_status_masks_need_status_register():
    doc = copy.deepcopy(SIM_DOC)
    del doc["registers"]["status"]
    with pytest.raises(DriveConfigError, match=r"\[status\] enabled_mask: status masks need"):
        parse_map(doc, "m.toml")


def test_fc23_needs_holding_feedback():
    doc = copy.deepcopy(SIM_DOC)
    for name in ("status", "fault", "timestamp", "velocity", "position"):
        doc["registers"][name]["type"] = "input"
    with pytest.raises(DriveConfigError, match=r"\[map\] fc23: FC23 reads holding"):
        parse_map(doc, "m.toml")
    doc["map"]["fc23"] = False
    assert parse_map(doc, "m.toml").feedback.kind == "input"


def test_feedback_blocks_respect_gaps_and_put_velocity_first():
    doc = copy.deepcopy(SIM_DOC)
    doc["registers"]["velocity"]["address"] = 0x0040  # 0x18 registers after position ends
    m = parse_map(doc, "m.toml")
    assert [b.names for b in m.blocks] == [
        ("velocity",),
        ("status", "fault", "timestamp"),
        ("position",),
    ]
    doc["map"]["max_gap"] = 2  # the hole where velocity was may be read across
    m = parse_map(doc, "m.toml")
    assert [b.names for b in m.blocks] == [
        ("velocity",),
        ("status", "fault", "timestamp", "position"),
    ]
    assert (m.blocks[1].address, m.blocks[1].count) == (0x20, 8)
    doc["map"]["max_gap"] = 0x18
    assert len(parse_map(doc, "m.toml").blocks) == 1


# ------------------------------------------------------------ units, fc23, turnaround
def test_register_units_give_the_drive_units():
    sim, z = load_map("servobench-sim"), load_map("zlac8015d")
    assert sim.signal_units == {"u": "N m", "v": "rad/s", "x": "rad"}
    assert z.signal_units == {"u": "A", "v": "rad/s", "x": "inc"}
    assert sim["timestamp"].unit == sim["watchdog"].unit == "s"
    # 0.1 r/min per count, in rad/s: 0.1 * 2 pi / 60
    assert z["velocity"].scale == pytest.approx(0.1 * 2 * 3.141592653589793 / 60, rel=1e-15)


def test_fc23_auto_and_turnaround():
    doc = copy.deepcopy(SIM_DOC)
    doc["map"]["fc23"] = "auto"
    m = parse_map(doc, "m.toml")
    assert (m.fc23, m.fc23_auto, m.turnaround_s) == (True, True, 0.0005)
    doc["map"]["fc23"] = False
    del doc["map"]["turnaround_ms"]
    m = parse_map(doc, "m.toml")
    assert (m.fc23, m.fc23_auto, m.turnaround_s) == (False, False, 0.0)
    del doc["registers"]["velocity"]["unit"]
    doc["units"] = {"v": "rpm"}
    assert parse_map(doc, "m.toml").signal_units["v"] == "rpm"  # [units] where a register names none
