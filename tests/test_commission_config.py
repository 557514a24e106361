"""bench.toml parsing, the shipped example, limit merging and the limits in the drive URL."""

from __future__ import annotations

import io
import math
from pathlib import Path

import pytest

from servobench.bench.commission.config import LimitSettings, load_config, parse_config
from servobench.bench.commission.errors import CommissionRefused
from servobench.bench.commission.limits import (
    ConfirmedLimits,
    TerminalPrompter,
    confirm_at_terminal,
    limits_from_config,
    merge_limits,
    url_with_limits,
)
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import UsageError

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "bench.toml"


def test_the_example_config_loads_with_every_limit():
    cfg = load_config(EXAMPLE)
    assert cfg.limits.missing() == []
    assert cfg.bump.fractions and cfg.design.phase_margin_deg > 0
    limits = limits_from_config(cfg.limits)
    assert limits.max_u > 0 and limits.max_v > 0


def test_infinite_travel_and_defaults():
    cfg = parse_config({"limits": {"max_u": 2, "max_v": 3, "xmin": -math.inf, "xmax": math.inf}})
    assert cfg.limits == LimitSettings(2.0, 3.0, -math.inf, math.inf)
    assert cfg.bump.fs_hz is None and cfg.sidbe == {}  # None: the rate the drive's link carries


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"limit": {}}, "unknown table"),
        ({"limits": {"max_U": 1}}, "unknown key"),
        ({"limits": {"max_u": "5"}}, "must be a number"),
        ({"limits": {"max_u": math.inf}}, "finite"),
        ({"bump": {"fractions": [0.9]}}, "fractions"),
        ({"bump": {"fractions": 0.1}}, "list"),
        ({"design": {"phase_margin_deg": 95}}, "phase_margin_deg"),
        ({"compensation": {"sign_band": 2}}, "sign_band"),
        ({"sidbe": 3}, "must be a table"),
    ],
)
def test_config_errors_are_clear(data, match):
    with pytest.raises(UsageError, match=match):
        parse_config(data, "t.toml")


def test_unreadable_and_invalid_files(tmp_path):
    with pytest.raises(UsageError, match="cannot read"):
        load_config(tmp_path / "nope.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[limits\n")
    with pytest.raises(UsageError, match="not valid TOML"):
        load_config(bad)


def test_missing_limits_under_yes_are_named():
    with pytest.raises(CommissionRefused, match=r"missing: max_v, xmin, xmax"):
        limits_from_config(LimitSettings(max_u=1.0))


def test_merge_takes_the_tighter_limit():
    url = parse_drive_url("sim://?max_u=2&xmin=-1")
    merged = merge_limits(LimitSettings(max_u=5.0, max_v=3.0, xmin=-5.0, xmax=1.0), url)
    assert merged == LimitSettings(2.0, 3.0, -1.0, 1.0)


def test_limits_go_into_the_url_and_the_drive_enforces_them():
    limits = ConfirmedLimits(1.5, 4.0, -2.0, math.inf)
    url = url_with_limits("sim://?M=0.1&max_u=9&pace=fast", limits)
    parsed = parse_drive_url(url)
    assert parsed.query == {"M": "0.1", "pace": "fast", "max_u": "1.5", "max_v": "4.0", "xmin": "-2.0"}
    with open_drive(url) as drive:
        assert drive.limits.max_command == 1.5 and drive.limits.min_position == -2.0
        drive.enable()
        _, applied = drive.exchange(10.0)
        assert applied == 1.5
    tcp = url_with_limits("modbus+tcp://127.0.0.1:5020?unit=1", limits)
    assert tcp.startswith("modbus+tcp://127.0.0.1:5020?unit=1&max_u=1.5")


def test_confirmed_limits_validate():
    with pytest.raises(CommissionRefused, match="max_u"):
        ConfirmedLimits(0.0, 1.0, -1.0, 1.0)
    with pytest.raises(CommissionRefused, match="xmin < xmax"):
        ConfirmedLimits(1.0, 1.0, 1.0, -1.0)


def test_terminal_confirmation_reads_the_answers():
    from rich.console import Console

    console = Console(file=io.StringIO())
    answers = io.StringIO("3\n\n-inf\ninf\ny\n")  # max_v: accept the configured default
    limits = confirm_at_terminal(LimitSettings(max_v=7.0), TerminalPrompter(console, answers))
    assert (limits.max_u, limits.max_v, limits.xmin, limits.xmax) == (3.0, 7.0, -math.inf, math.inf)
    declined = io.StringIO("3\n7\n-1\n1\nn\n")
    with pytest.raises(CommissionRefused, match="not confirmed"):
        confirm_at_terminal(LimitSettings(), TerminalPrompter(console, declined))


def test_end_of_input_refuses_instead_of_looping():
    from rich.console import Console

    prompter = TerminalPrompter(Console(file=io.StringIO()), io.StringIO("3\n"))
    with pytest.raises(CommissionRefused, match="end of input"):
        confirm_at_terminal(LimitSettings(), prompter)


def test_identity_keys_for_the_record():
    cfg = parse_config({"identity": {"site": " Hall 3 ", "machine": "Press 7", "axis": "Z", "operator": "A. T."}})
    assert cfg.identity.as_dict() == {"site": "Hall 3", "machine": "Press 7", "axis": "Z", "operator": "A. T."}
    assert load_config(EXAMPLE).identity.axis == "X"  # documented in the shipped example
    assert parse_config({}).identity.site == ""
    with pytest.raises(UsageError, match=r"\[identity\]: unknown key\(s\) opertor"):
        parse_config({"identity": {"opertor": "x"}}, "t.toml")
    with pytest.raises(UsageError, match="axis must be a string"):
        parse_config({"identity": {"axis": 3}}, "t.toml")
