"""Serial ASCII dialects: loading, validation, line codec, templates (pure, no I/O)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from servobench.drivers.serial.ascii_line import (
    MalformedReplyError,
    decode_reply,
    decode_request,
    encode_line,
    xor_checksum,
)
from servobench.drivers.serial.dialect import (
    COMMAND_SPECS,
    DIALECT_DIR,
    CommandRejectedError,
    load_dialect,
    parse_dialect,
)
from servobench.errors import DriveConfigError, DriveConnectionError, DriveError, UsageError

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


@pytest.fixture(scope="module")
def odrive():
    return load_dialect("odrive")


def _odrive_table() -> dict:
    return tomllib.loads((DIALECT_DIR / "odrive.toml").read_text(encoding="utf-8"))


# ------------------------------------------------------------ checksum golden vectors
@pytest.mark.parametrize(
    ("body", "checksum"),
    [
        ("r vbus_voltage ", 93),  # the ODrive documentation's example: "r vbus_voltage *93"
        ("r vbus_voltage", 125),
        ("f 0", 118),  # 0x66 ^ 0x20 ^ 0x30 = 0x76
        ("c 0 0.5", 120),  # 0x63^0x20^0x30^0x20^0x30^0x2E^0x35 = 0x78
        ("", 0),
    ],
)
def test_xor_checksum_golden(body, checksum):
    assert xor_checksum(body) == checksum
    assert xor_checksum(body.encode()) == checksum


def test_encode_line_with_and_without_checksum():
    assert encode_line("f 0", b"\n", checksum=False) == b"f 0\n"
    assert encode_line("f 0", b"\n", checksum=True) == b"f 0*118\n"
    assert encode_line("r vbus_voltage ", b"\n", checksum=True) == b"r vbus_voltage *93\n"
    assert (
        encode_line("0.5 1.0", b"\r\n", checksum=True)
        == b"0.5 1.0*" + b"%d" % xor_checksum("0.5 1.0") + b"\r\n"
    )


@pytest.mark.parametrize("body", ["f 0\n", "c 0 \u00b5"])
def test_encode_line_rejects_breaks_and_non_ascii(body):
    with pytest.raises(UsageError):
        encode_line(body, b"\n", checksum=False)


def test_decode_reply_good_lines():
    assert decode_reply(b"0.500000 -1.250000\r", expect_checksum=False) == "0.500000 -1.250000"
    assert decode_reply(b"24.087744", expect_checksum=False) == "24.087744"
    raw = encode_line("0.500000 -1.250000", b"\r\n", checksum=True).rstrip(b"\r\n")
    assert decode_reply(raw, expect_checksum=True) == "0.500000 -1.250000"


@pytest.mark.parametrize(
    ("raw", "checksum", "why"),
    [
        (b"0.5 1.0*12", True, "checksum 12"),  # wrong checksum
        (b"0.5 1.0", True, "no checksum"),  # missing checksum
        (b"0.5 1.0*", True, "no checksum"),  # truncated checksum
        (b"0.5 1.0*ab", True, "no checksum"),  # not a number
        (b"0.5 1.0*" + b"%d" % xor_checksum("0.5 1.0"), False, "nobody asked"),
        (b"0.5 \xff1.0", False, "not ASCII"),
        (b"0.5\x001.0", False, "control characters"),
    ],
)
def test_decode_reply_malformed_is_typed(raw, checksum, why):
    with pytest.raises(MalformedReplyError, match=why) as info:
        decode_reply(raw, expect_checksum=checksum)
    assert isinstance(info.value, DriveConnectionError)


def test_decode_request_like_the_odrive():
    assert decode_request(b"f 0").body == "f 0"
    ok = decode_request(b"r vbus_voltage *93")
    assert (ok.body, ok.checksummed, ok.valid) == ("r vbus_voltage", True, True)
    bad = decode_request(b"r vbus_voltage *94")
    assert bad.checksummed and not bad.valid
    assert decode_request(b"c 0 1.5 ; torque step").body == "c 0 1.5"
    assert not decode_request(b"c 0 \xff").valid
    assert not decode_request(b"f 0*x").valid


# ------------------------------------------------------------ the shipped dialect
def test_odrive_dialect_loads_with_docs(odrive):
    assert odrive.name == "odrive"
    assert odrive.reference.startswith("https://docs.odriverobotics.com/")
    assert odrive.firmware == "0.5.x"
    assert dict(odrive.units) == {"u": "N m", "v": "turn/s", "x": "turn"}  # SI spelling of servobench.units
    assert odrive.terminator == b"\n" and odrive.reply_terminator == b"\r\n"
    assert odrive.checksum == "xor" and odrive.use_checksum is False
    assert odrive.states == {"enabled": 8, "disabled": 1}
    assert odrive.watchdog_error == 0x800
    assert odrive.extensions == {"set_cycle", "cycle_readback"}


@pytest.mark.parametrize(
    ("command", "values", "line"),
    [
        ("torque", {"axis": 0, "u": -0.25}, "c 0 -0.25"),
        ("torque", {"axis": 1, "u": 1e-9}, "c 1 1e-09"),
        ("feedback", {"axis": 0}, "f 0"),
        ("enable", {"axis": 0}, "w axis0.requested_state 8"),
        ("disable", {"axis": 0}, "w axis0.requested_state 1"),
        ("state", {"axis": 0}, "r axis0.current_state"),
        ("error", {"axis": 0}, "r axis0.error"),
        ("clear_errors", {"axis": 0}, "sc"),
        ("watchdog_timeout", {"axis": 0, "timeout_s": 0.5}, "w axis0.config.watchdog_timeout 0.5"),
        ("watchdog_enable", {"axis": 0}, "w axis0.config.enable_watchdog 1"),
        ("watchdog_feed", {"axis": 0}, "u 0"),
        ("vbus", {"axis": 0}, "r vbus_voltage"),
        ("info", {"axis": 0}, "i"),
        ("set_cycle", {"axis": 0, "period_s": 0.001}, "w axis0.config.servobench_cycle 0.001"),
    ],
)
def test_odrive_requests_format_and_round_trip(odrive, command, values, line):
    assert odrive.request(command, **values) == line
    parsed = odrive.match_request(line)
    assert parsed is not None and parsed.name == command
    for key, value in parsed.fields.items():
        assert value == pytest.approx(values[key])


def test_every_spec_command_of_odrive_matches_itself(odrive):
    for name in odrive.commands:
        body = odrive.request(name, axis=0, u=0.5, timeout_s=0.25, period_s=0.002)
        assert odrive.match_request(body).name == name


def test_non_finite_command_is_refused(odrive):
    for bad in (float("nan"), float("inf")):
        with pytest.raises(UsageError, match="not finite"):
            odrive.request("torque", axis=0, u=bad)


def test_request_of_missing_command_is_config_error(odrive):
    with pytest.raises(DriveConfigError, match="quick_stop"):
        odrive.request("quick_stop", axis=0)


def test_match_request_tolerates_whitespace_and_rejects_noise(odrive):
    assert odrive.match_request("  c   0   +.5 ").fields == {"axis": 0, "u": 0.5}
    assert odrive.match_request("w axis0.requested_state 3") is None
    assert odrive.match_request("c 0") is None
    assert odrive.match_request("hello") is None


@pytest.mark.parametrize(
    ("name", "body", "fields"),
    [
        ("feedback", "0.500000 -1.250000", {"x": 0.5, "v": -1.25}),
        ("feedback", "-2.5e-03 1E+2", {"x": -2.5e-3, "v": 100.0}),
        ("state", "8", {"state": 8}),
        ("error", "2048", {"code": 0x800}),
        ("error", "0x800", {"code": 0x800}),
        ("error", "010", {"code": 10}),
        ("vbus", "24.087744", {"value": 24.087744}),
        ("cycle", "0.001000", {"period_s": 0.001}),
    ],
)
def test_parse_good_replies(odrive, name, body, fields):
    parsed = odrive.parse_reply(name, body)
    assert parsed.name == name
    assert parsed.fields == pytest.approx(fields)


@pytest.mark.parametrize(
    ("name", "body"),
    [
        ("feedback", "0.500000"),  # truncated after the first number
        ("feedback", "0.50?000 -1.25"),  # garbled digit
        ("feedback", "0.5 -1.25 3.0"),  # one number too many
        ("feedback", "nan 0.0"),  # not finite
        ("feedback", ""),  # empty line
        ("state", "8.0"),  # float where an int belongs
        ("error", "lu"),  # the firmware bug of ODrive issue #571
        ("vbus", "24.0V"),
    ],
)
def test_parse_malformed_replies_is_typed(odrive, name, body):
    with pytest.raises(MalformedReplyError, match=name):
        odrive.parse_reply(name, body)


def test_rejections_are_recognised(odrive):
    assert odrive.rejection("invalid property") == "property"
    assert odrive.rejection("invalid motor 3") == "axis"
    assert odrive.rejection("unknown command") == "unknown"
    assert odrive.rejection("0.5 1.0") is None
    assert odrive.rejection("invalid propertyX") is None
    assert issubclass(CommandRejectedError, DriveError)


def test_describe_error_names_flags(odrive):
    assert odrive.describe_error(0x800) == "0x00000800 (WATCHDOG_TIMER_EXPIRED)"
    assert odrive.describe_error(0x840) == "0x00000840 (MOTOR_FAILED | WATCHDOG_TIMER_EXPIRED)"
    assert odrive.describe_error(0x2) == "0x00000002"


def test_info_templates(odrive):
    assert odrive.info["firmware"].parse("Firmware version: 0.5.6") == {"text": "0.5.6"}
    assert odrive.info["serial_number"].parse("Hardware version: 3.6-56V") is None


# ------------------------------------------------------------ validation
def _write(tmp_path: Path, table: dict) -> Path:
    lines = []

    def emit(prefix: str, t: dict) -> None:
        scalars = {k: v for k, v in t.items() if not isinstance(v, dict)}
        if prefix:
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            if isinstance(v, str):
                v = (
                    '"'
                    + v.replace("\\", "\\\\")
                    .replace('"', '\\"')
                    .replace("\n", "\\n")
                    .replace("\r", "\\r")
                    + '"'
                )
            elif isinstance(v, bool):
                v = "true" if v else "false"
            lines.append(f"{k} = {v}")
        for k, v in t.items():
            if isinstance(v, dict):
                emit(f"{prefix}.{k}" if prefix else k, v)

    emit("", table)
    path = tmp_path / "custom.toml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_a_dialect_file_by_path_loads(tmp_path):
    path = _write(tmp_path, _odrive_table())
    d = load_dialect(str(path))
    assert d.source == str(path)
    assert d.request("torque", axis=0, u=1.0) == "c 0 1"


def _mutated(change) -> dict:
    table = _odrive_table()
    change(table)
    return table


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda t: t["commands"].pop("torque"), r"\[commands\].*missing key 'torque'"),
        (lambda t: t["commands"].update(torqe="c {axis} {u}"), r"\[commands\].*unknown key.*torqe"),
        (
            lambda t: t["commands"].update(torque="c {axis} {w}"),
            r"\[commands\] torque: unknown field \{w\}",
        ),
        (
            lambda t: t["commands"].update(torque="c {axis} {u:.3f}"),
            r"torque: field \{u\} must appear once, bare",
        ),
        (lambda t: t["commands"].update(torque="c {axis} {u"), r"torque: malformed template"),
        (lambda t: t["commands"].update(torque=3), r"torque: must be a non-empty string"),
        (
            lambda t: t["replies"].update(feedback="{x}"),
            r"\[replies\] feedback: must hold field\(s\) v",
        ),
        (lambda t: t["replies"].pop("state"), r"missing key 'state' \(reply of state\)"),
        (lambda t: t.pop("states"), r"missing table \[states\]"),
        (lambda t: t["states"].update(enabled="8"), r"\[states\]: enabled must be a int"),
        (lambda t: t["states"].update(enabled=True), r"\[states\]: enabled must be a int"),
        (lambda t: t["dialect"].update(checksum="crc"), r"\[dialect\]: checksum must be"),
        (
            lambda t: t["dialect"].update(checksum="none", use_checksum=True),
            r"use_checksum = true needs",
        ),
        (lambda t: t["dialect"].update(terminator=";"), r"\[dialect\]: terminator must be"),
        (
            lambda t: t["dialect"].update(float_format="d"),
            r"float_format 'd' is not a float format",
        ),
        (lambda t: t["dialect"].update(baud=9600), r"\[dialect\]: unknown key\(s\) baud"),
        (
            lambda t: t["extensions"].pop("cycle_readback"),
            r"set_cycle and cycle_readback go together",
        ),
        (lambda t: t["extensions"].update(torque="c {axis} {u}"), r"\[extensions\]: unknown key"),
        (
            lambda t: t["errors"].update(watchdog="NOPE"),
            r"\[errors\]: watchdog = 'NOPE' is not a flag",
        ),
        (lambda t: t["rejections"].pop("axis"), r"\[rejections\]: missing key 'axis'"),
        (lambda t: t.update(extra={"a": 1}), r"unknown key\(s\) extra"),
        (lambda t: t["units"].pop("v"), r"\[units\]: missing key 'v'"),
        (lambda t: t.pop("info"), r"missing table \[info\]"),
    ],
)
def test_invalid_dialects_name_file_and_key(tmp_path, change, message):
    path = _write(tmp_path, _mutated(change))
    with pytest.raises(DriveConfigError, match=message) as info:
        load_dialect(str(path))
    assert str(path) in str(info.value)


def test_not_toml_and_missing_file_and_unknown_name(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[dialect\nname = 1\n", encoding="utf-8")
    with pytest.raises(DriveConfigError, match="not valid TOML"):
        load_dialect(str(bad))
    with pytest.raises(DriveConfigError, match="cannot read dialect file"):
        load_dialect(str(tmp_path / "absent.toml"))
    with pytest.raises(
        DriveConfigError, match="unknown serial dialect 'odrivee'.*shipped: .*odrive"
    ):
        load_dialect("odrivee")
    with pytest.raises(DriveConfigError, match="not a dialect name"):
        load_dialect("od rive")


def test_parse_dialect_minimal_without_optional_commands():
    table = _odrive_table()
    for name, spec in COMMAND_SPECS.items():
        if not spec.required:
            table["commands"].pop(name, None)
    table.pop("extensions")
    table.pop("info")
    d = parse_dialect(table, "minimal")
    assert not d.has("set_cycle") and not d.has("info") and not d.extensions
