"""udev rules: the linter, the shipped templates, and ``servobench udev`` end to end."""

from __future__ import annotations

import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from servobench.udev.lint import KEYS, lint_file, lint_text
from servobench.udev.rules import (
    InstallOptions,
    UsageError,
    install,
    parse_can_name,
    render,
    rules_dir,
    shipped_rules,
    udev_glob,
    usb_matches,
)

SHIPPED = shipped_rules()
CLI_TIMEOUT_S = 60


def _servobench() -> list[str]:
    script = Path(sys.executable).with_name("servobench")
    found = str(script) if script.exists() else shutil.which("servobench")
    assert found, "the servobench console script is not installed"
    return [found]


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*_servobench(), "udev", *args],
        capture_output=True,
        text=True,
        timeout=CLI_TIMEOUT_S,
        check=False,
    )


# ----------------------------------------------------------------- shipped rules
def test_rules_are_found_in_the_source_checkout() -> None:
    assert rules_dir() == Path(__file__).resolve().parent.parent / "udev"
    assert [p.name for p in SHIPPED] == sorted(
        ["70-servobench-can.rules", "70-servobench-rs485.rules", "70-servobench-drives.rules"]
    )


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_shipped_template_lints_clean(path: Path) -> None:
    result = lint_file(path, template=True)
    assert result.findings == (), [str(f) for f in result.findings]
    assert len(result.rules) >= 10


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
@pytest.mark.parametrize(
    "options",
    [
        InstallOptions(),
        InstallOptions(
            bitrate=250_000,
            restart_ms=500,
            group="servobench",
            can_names=(
                parse_can_name("servocan0=serial:0043001F5734570420393235"),
                parse_can_name("benchcan1=path:pci-0000:00:14.0-usb-0:3:1.0"),
            ),
        ),
    ],
    ids=["defaults", "custom"],
)
def test_shipped_rules_render_and_lint_clean(path: Path, options: InstallOptions) -> None:
    text = render(path.read_text(encoding="utf-8"), options)
    assert "@" not in text.replace("@CAN_NAMES@", "")  # every variable filled
    result = lint_text(text, path.name)
    assert result.findings == (), [str(f) for f in result.findings]


@pytest.mark.parametrize("path", SHIPPED, ids=lambda p: p.name)
def test_unrendered_template_is_rejected_outside_template_mode(path: Path) -> None:
    errors = lint_file(path).errors
    assert errors and all("unfilled template variable @" in f.message for f in errors)


def test_ftdi_latency_timer_rule_is_on_the_usb_serial_port() -> None:
    rules = lint_file(rules_dir() / "70-servobench-rs485.rules", template=True).rules
    latency = [r for r in rules if any(t.attr == "latency_timer" for t in r.tokens)]
    assert len(latency) == 1
    tokens = {(t.key, t.attr, t.op, t.value) for t in latency[0].tokens}
    assert tokens == {
        ("ACTION", None, "==", "add"),
        ("SUBSYSTEM", None, "==", "usb-serial"),
        ("DRIVER", None, "==", "ftdi_sio"),
        ("ATTR", "latency_timer", "=", "1"),
    }


def test_can_bring_up_uses_full_paths_and_the_renamed_interface() -> None:
    text = render((rules_dir() / "70-servobench-can.rules").read_text(), InstallOptions())
    runs = [t.value for r in lint_text(text).rules for t in r.tokens if t.key == "RUN"]
    assert runs == [
        "/sbin/ip link set $name type can bitrate 1000000 restart-ms 100",
        "/sbin/ip link set $name up",
    ]


def test_shipped_rules_match_the_bench_adapters() -> None:
    matches = usb_matches(lint_file(p, template=True) for p in SHIPPED)

    def matched(vid: str, pid: str) -> bool:
        return any(udev_glob(m.vendor, vid) and udev_glob(m.product, pid) for m in matches)

    bench_ids = [
        ("0c72", "000c"), ("0c72", "0012"), ("0bfd", "0107"), ("1d50", "606f"),
        ("16d0", "117e"), ("ad50", "60c4"), ("0403", "6001"), ("0403", "6010"),
        ("0403", "6011"), ("0403", "6014"), ("0403", "6015"), ("1a86", "7523"),
        ("10c4", "ea60"), ("1209", "0d32"), ("0483", "df11"),
    ]  # fmt: skip
    for vid_pid in bench_ids:
        assert matched(*vid_pid), vid_pid
    assert not matched("0403", "6002")
    assert not matched("046d", "c52b")


# ----------------------------------------------------------------- linter
BAD_RULES = [
    ('KERNEL="ttyUSB0", MODE="0660"', "KERNEL is a match key: operator '='"),
    ('ACTION+="add", MODE="0660"', "ACTION is a match key: operator '+='"),
    ('KERNEL=="x", MODE=="0660"', "MODE is an assignment key: operator '=='"),
    ('KERNEL=="x", GOTO!="end"\nLABEL="end"', "GOTO is an assignment key"),
    ('KERNEL=="x", ENV{A}-="1"', "ENV{A} is a key: operator '-='"),
    ('KERNEL==ttyUSB0, MODE="0660"', "value of KERNEL is unquoted"),
    ("KERNEL=='ttyUSB0', MODE=\"0660\"", "value of KERNEL is single-quoted"),
    ('KERNEL=="ttyUSB0, MODE="0660"', "missing ','"),
    ('KERNEL=="ttyUSB0", MODE="0660', "unterminated quoted value of MODE"),
    ('ACTION=="add" SUBSYSTEM=="tty", MODE="0660"', "missing ',' between ACTION and 'SUBSYSTEM'"),
    ('KERNAL=="ttyUSB0", MODE="0660"', "unknown key KERNAL (did you mean KERNEL?)"),
    ('subsystem=="usb", MODE="0660"', "unknown key subsystem (did you mean SUBSYSTEM?)"),
    ('WAIT_FOR="x"', "WAIT_FOR is no longer supported"),
    ('KERNEL{x}=="a", MODE="0660"', "KERNEL takes no {attribute}"),
    ('ATTRS=="a", MODE="0660"', "ATTRS needs an {attribute}"),
    ('ATTR{idVendor=="0403", MODE="0660"', "unbalanced '{'"),
    ('KERNEL=="a", RUN{shell}+="/bin/true"', "RUN{shell}: the attribute must be one of"),
    ('KERNEL=="a", IMPORT{magic}="x"', "IMPORT{magic}: the attribute must be one of"),
    ('KERNEL=="a", MODE="rw-rw----"', "MODE 'rw-rw----' is not an octal mode"),
    ('KERNEL=="a", GROUP="two words"', "GROUP 'two words' is not a user or group name"),
    ('KERNEL=="a", SYMLINK+="x-$serial"', "unknown substitution '$serial'"),
    ('KERNEL=="a", SYMLINK+="x-%z"', "unknown substitution '%z'"),
    ('SUBSYSTEM=="net", NAME="servobench-can-0"', "NAME 'servobench-can-0': 1-15 characters"),
    ('KERNEL=="a", GOTO="end"', "GOTO 'end' has no LABEL after it"),
    ('LABEL="end"\nKERNEL=="a", GOTO="end"', "GOTO 'end' has no LABEL after it"),
    ('KERNEL=="a", MODE="0660" # note', "comments must be on a line of their own"),
    ('KERNEL=="a", \\', "line continuation at the end of the file"),
    ('KERNEL=="a", GROUP="@GROUP@"', "unfilled template variable @GROUP@"),
    ('KERNEL=="a", TEST{rw}=="x", MODE="0660"', "TEST{rw}: the attribute is an octal mode"),
]


@pytest.mark.parametrize(("text", "message"), BAD_RULES, ids=[m for _, m in BAD_RULES])
def test_linter_rejects(text: str, message: str) -> None:
    errors = lint_text(text, "bad.rules").errors
    assert any(message in f.message for f in errors), [str(f) for f in errors]


GOOD_RULES = """\
# a comment, then a blank line

ACTION=="add|change", SUBSYSTEM=="tty", ATTRS{idVendor}=="0403", MODE="0660", GROUP="dialout"
KERNEL=="ttyUSB[0-9]*", ENV{ID_SERIAL_SHORT}=="?*", SYMLINK+="x/$env{ID_SERIAL_SHORT}-%n"
  SUBSYSTEM=="net", ACTION=="add", \\
# comments inside a continued rule are skipped by udev
    ATTR{type}=="280", NAME="servocan%n"
KERNEL=="a", PROGRAM=="/bin/echo %k", RESULT=="a*", SYMLINK+="by-result/%c{1+}"
KERNEL=="a", IMPORT{builtin}="usb_id", IMPORT{program}="/usr/bin/id-helper $devnode"
KERNEL=="a", TEST{0644}=="power/control", ATTR{power/control}="auto"
KERNEL=="a", ENV{X}="has \\"quotes\\" and $$ and %%", OPTIONS+="link_priority=10,nowatch"
KERNEL=="a", RUN{builtin}+="kmod load can", RUN+="/bin/sh -c 'echo ok'", TAG+="systemd"
KERNEL=="a", SYMLINK+=e"esc\\\\aped", CONST{virt}=="docker"
ACTION!="add", GOTO="end"
LABEL="end"
"""


def test_linter_accepts_valid_rules() -> None:
    result = lint_text(GOOD_RULES, "good.rules")
    assert result.errors == (), [str(f) for f in result.errors]
    assert [str(f) for f in result.warnings] == [
        "good.rules:6: warning: comment inside a continued rule (udev skips it)"
    ]
    assert len(result.rules) == 11
    env = next(t for r in result.rules for t in r.tokens if t.key == "ENV" and t.op == "=")
    assert env.value == 'has "quotes" and $$ and %%'
    esc = next(t for r in result.rules for t in r.tokens if t.value.startswith("esc"))
    assert esc.value == "esc\\aped"


def test_findings_point_at_the_physical_line_of_a_continued_rule() -> None:
    text = 'KERNEL=="a", \\\n  MODE="0660", \\\n  SYMLNK+="x"\nKERNEL=="b", GROUP+="g"\n'
    found = [str(f) for f in lint_text(text, "c.rules").findings]
    assert found == [
        "c.rules:3: error: unknown key SYMLNK (did you mean SYMLINK?)",
        "c.rules:4: warning: udev reads GROUP+= as GROUP=; write '='",
    ]


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('KERNEL=="a", GROUP+="g"', "udev reads GROUP+= as GROUP="),
        ('KERNEL=="a", NAME+="x"', "udev reads NAME+= as NAME="),
        ('KERNEL=="a", MODE="0660",', "trailing ','"),
        ('KERNEL=="a", RUN+="ip link set %k up"', "RUN program is not an absolute path"),
        ('KERNEL=="a", SUBSYSTEM=="tty"', "rule only matches: it has no effect"),
        ('ACTION=="plug", MODE="0660"', "ACTION 'plug' is not one of"),
        ('KERNEL=="a", OPTIONS+="turbo"', "unknown OPTIONS entry 'turbo'"),
    ],
)
def test_linter_warns_on_what_udev_accepts_reluctantly(text: str, message: str) -> None:
    result = lint_text(text)
    assert result.errors == ()
    assert any(message in f.message for f in result.warnings), [str(f) for f in result.findings]


def _value_text() -> st.SearchStrategy[str]:
    return st.text(
        st.characters(whitelist_categories=("L", "N"), whitelist_characters=" ._-*?[]|/")
    )


@st.composite
def _tokens(draw: st.DrawFn) -> list[tuple[str, str | None, str, str]]:
    tokens = []
    for key in draw(st.lists(st.sampled_from(sorted(KEYS)), min_size=1, max_size=6)):
        spec = KEYS[key]
        attr = None
        if spec.attr == "required" or (spec.attr == "optional" and draw(st.booleans())):
            attr = draw(st.sampled_from(sorted(spec.attr_values))) if spec.attr_values else "a/b_c"
            attr = "0644" if key == "TEST" else attr
        tokens.append((key, attr, draw(st.sampled_from(sorted(spec.ops))), draw(_value_text())))
    return tokens


@settings(max_examples=150, deadline=None)
@given(tokens=_tokens(), sep=st.sampled_from([",", ", ", " ,  "]))
def test_tokenizer_round_trips_any_well_formed_rule(tokens: list, sep: str) -> None:
    line = sep.join(
        f'{k}{"{" + a + "}" if a is not None else ""}{op}"{v}"' for k, a, op, v in tokens
    )
    result = lint_text(line)
    syntax = [f for f in result.errors if "operator" in f.message or "missing" in f.message]
    assert syntax == []
    assert [(t.key, t.attr, t.op, t.value) for r in result.rules for t in r.tokens] == tokens


# ----------------------------------------------------------------- options
@pytest.mark.parametrize(
    "spec", ["servocan0", "x=serial:", "x=uuid:12", "way-too-long-name=serial:1", "a=serial:1*"]
)
def test_bad_can_names_are_refused(spec: str) -> None:
    with pytest.raises(UsageError):
        parse_can_name(spec)


def test_install_refuses_rules_that_do_not_lint(tmp_path: Path) -> None:
    src = tmp_path / "99-broken.rules"
    src.write_text('KERNEL="x", GROUP="@GROUP@"\n')
    with pytest.raises(UsageError, match="do not lint clean"):
        install(tmp_path / "root", InstallOptions(), sources=[src])
    assert not (tmp_path / "root").exists()


# ----------------------------------------------------------------- CLI
def test_cli_install_into_a_temporary_root(tmp_path: Path) -> None:
    proc = run_cli(
        "install", "--root", str(tmp_path), "--bitrate", "250000", "--group", "servobench",
        "--can-name", "servocan1=serial:ABC123",
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    target = tmp_path / "etc/udev/rules.d"
    assert sorted(p.name for p in target.iterdir()) == [p.name for p in SHIPPED]
    for p in target.iterdir():
        assert stat.S_IMODE(p.stat().st_mode) == 0o644
        text = p.read_text()
        assert "@GROUP@" not in text and "@BITRATE@" not in text and "@RESTART_MS@" not in text
        assert 'GROUP="servobench"' in text
    can = (target / "70-servobench-can.rules").read_text()
    assert 'RUN+="/sbin/ip link set $name type can bitrate 250000 restart-ms 100"' in can
    assert 'ATTRS{serial}=="ABC123", NAME="servocan1"' in can
    assert "servocan%n" not in can
    assert "udevadm control --reload-rules && udevadm trigger" in proc.stdout
    check = run_cli("lint", *(str(p) for p in sorted(target.iterdir())))
    assert check.returncode == 0, check.stdout
    assert "3 files" in check.stdout and "0 errors, 0 warnings" in check.stdout


def test_cli_install_defaults_and_overwrite(tmp_path: Path) -> None:
    for _ in range(2):  # installing again replaces the files
        proc = run_cli("install", "--root", str(tmp_path))
        assert proc.returncode == 0, proc.stderr
    can = (tmp_path / "etc/udev/rules.d/70-servobench-can.rules").read_text()
    assert 'NAME=="", NAME="servocan%n"' in can
    assert "bitrate 1000000 restart-ms 100" in can
    assert not list((tmp_path / "etc/udev/rules.d").glob(".*tmp"))


def test_cli_dry_run_writes_nothing(tmp_path: Path) -> None:
    proc = run_cli("install", "--root", str(tmp_path), "--dry-run", "--bitrate", "125000")
    assert proc.returncode == 0, proc.stderr
    assert "bitrate 125000" in proc.stdout and "# ---- 70-servobench-rs485.rules" in proc.stdout
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--root", "{file}"], "cannot write udev rules to"),
        (["--root", "{file}/sub"], "cannot write udev rules to"),
        (["--root", "{tmp}", "--bitrate", "0"], "bitrate 0 bit/s is outside"),
        (["--root", "{tmp}", "--bitrate", "2000000"], "bitrate 2000000 bit/s is outside"),
        (["--root", "{tmp}", "--group", "Bench Users"], "is not a valid group name"),
        (["--root", "{tmp}", "--can-name", "can0"], "expected NAME=serial:SERIAL"),
    ],
)
def test_cli_install_refuses_in_one_line(tmp_path: Path, args: list[str], message: str) -> None:
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the root should be\n")
    args = [a.format(file=blocker, tmp=tmp_path / "root") for a in args]
    proc = run_cli("install", *args)
    assert proc.returncode == 1
    assert proc.stdout == ""
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("servobench: error: "), proc.stderr
    assert message in lines[0]
    assert not (tmp_path / "root").exists()


def test_cli_lint_reports_file_and_line(tmp_path: Path) -> None:
    bad = tmp_path / "90-bad.rules"
    bad.write_text('# fine\nKERNEL=="ttyUSB0", MODE="0660"\nKERNEL="ttyUSB1", MODE="0660"\n')
    proc = run_cli("lint", str(bad))
    assert proc.returncode == 1
    assert f"{bad}:3: error: KERNEL is a match key" in proc.stdout
    assert "1 files, 2 rules: 1 errors, 0 warnings" in proc.stdout


def test_cli_lint_strict_fails_on_warnings(tmp_path: Path) -> None:
    soft = tmp_path / "91-soft.rules"
    soft.write_text('KERNEL=="ttyUSB0", GROUP+="dialout"\n')
    assert run_cli("lint", str(soft)).returncode == 0
    assert run_cli("lint", "--strict", str(soft)).returncode == 1


def test_cli_lint_shipped_rules_by_default() -> None:
    proc = run_cli("lint")
    assert proc.returncode == 0, proc.stdout
    assert "6 files" in proc.stdout and "0 errors, 0 warnings" in proc.stdout


def test_cli_list_shows_present_adapters(tmp_path: Path) -> None:
    devices = tmp_path / "bus/usb/devices"
    for port, vid, pid, serial, product in [
        ("1-2", "0403", "6001", "A10KXYZ", "FT232R USB UART"),
        ("1-3", "046d", "c52b", "", "Unifying Receiver"),
        ("1-4", "1209", "0d32", "206F3694424D", "ODrive 3.6 CDC Interface"),
    ]:
        d = devices / port
        d.mkdir(parents=True)
        for name, value in (
            ("idVendor", vid),
            ("idProduct", pid),
            ("serial", serial),
            ("product", product),
        ):
            if value:
                (d / name).write_text(value + "\n")
    (devices / "1-2:1.0").mkdir()  # interfaces have no idVendor
    proc = run_cli("list", "--sysfs", str(tmp_path))
    assert proc.returncode == 0, proc.stderr
    present = proc.stdout.split("plugged in now:")[1]
    assert "1-2" in present and "0403:6001" in present and "70-servobench-rs485.rules" in present
    assert (
        "1-4" in present and "206F3694424D" in present and "70-servobench-drives.rules" in present
    )
    assert "1-3" not in present and "1-2:1.0" not in present
    assert "0c72:000c|000d|0011|0012|0013|0014" in proc.stdout
