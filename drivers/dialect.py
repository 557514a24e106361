"""Serial ASCII dialects: line-based drive protocols described by a TOML file.

A dialect names, for one family of drives, the text of every request the
serial backend sends (torque command, feedback query, enable, state and
error reads, watchdog set-up and feed, clear errors ...), the shape of the
replies, the line terminators and the checksum rule. Both sides use it: the
host (:mod:`servobench.drivers.serial_ascii`) formats requests and parses replies, the
served simulator (:mod:`servobench.sim_backend.servers.serve_serial`) parses requests and
formats replies, so the two agree by construction.

Everything here is pure: text in, text or frozen dataclasses out, no I/O.

Templates (``"c {axis} {u}"``) are :class:`servobench.drivers.line_template.Template`;
line framing and checksums are in :mod:`servobench.drivers.ascii_line`.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from servobench.drivers.ascii_line import MalformedReplyError
from servobench.drivers.line_template import Template
from servobench.errors import DriveConfigError, DriveError
from servobench.tomlfile import read_toml

if sys.version_info >= (3, 11):
    pass
else:  # pragma: no cover
    pass

#: Folder of the shipped dialects (``dialect=NAME`` means ``NAME.toml`` here).
DIALECT_DIR = Path(__file__).parent / "data" / "dialects"
#: Dialect used when the URL names none.
DEFAULT_DIALECT = "odrive"


class CommandRejectedError(DriveError):
    """The drive answered a request with one of the dialect's rejection messages."""


@dataclass(frozen=True)
class CommandSpec:
    """What a dialect command may contain: its fields, the reply it expects, if required."""

    fields: frozenset[str]
    reply: str | None = None
    required: bool = True


#: Every request a dialect may define, in ``[commands]`` (or ``[extensions]``).
COMMAND_SPECS: dict[str, CommandSpec] = {
    "torque": CommandSpec(frozenset({"axis", "u"})),
    "feedback": CommandSpec(frozenset({"axis"}), reply="feedback"),
    "enable": CommandSpec(frozenset({"axis"})),
    "disable": CommandSpec(frozenset({"axis"})),
    "state": CommandSpec(frozenset({"axis"}), reply="state"),
    "error": CommandSpec(frozenset({"axis"}), reply="error"),
    "clear_errors": CommandSpec(frozenset({"axis"})),
    "watchdog_timeout": CommandSpec(frozenset({"axis", "timeout_s"})),
    "watchdog_enable": CommandSpec(frozenset({"axis"})),
    "watchdog_feed": CommandSpec(frozenset({"axis"})),
    "watchdog_readback": CommandSpec(frozenset({"axis"}), "watchdog_timeout", required=False),
    "position": CommandSpec(frozenset({"axis"}), reply="position", required=False),
    "velocity": CommandSpec(frozenset({"axis"}), reply="velocity", required=False),
    "vbus": CommandSpec(frozenset({"axis"}), reply="vbus", required=False),
    "info": CommandSpec(frozenset({"axis"}), required=False),
    "quick_stop": CommandSpec(frozenset({"axis"}), required=False),
    "set_cycle": CommandSpec(frozenset({"axis", "period_s"}), required=False),
    "cycle_readback": CommandSpec(frozenset({"axis"}), reply="cycle", required=False),
}
#: Commands allowed in ``[extensions]`` (servobench additions a stock drive rejects).
EXTENSION_COMMANDS = frozenset({"set_cycle", "cycle_readback"})
#: Reply name -> the fields its template must hold, all of them.
REPLY_FIELDS: dict[str, frozenset[str]] = {
    "feedback": frozenset({"x", "v"}),
    "state": frozenset({"state"}),
    "error": frozenset({"code"}),
    "watchdog_timeout": frozenset({"timeout_s"}),
    "position": frozenset({"x"}),
    "velocity": frozenset({"v"}),
    "vbus": frozenset({"value"}),
    "cycle": frozenset({"period_s"}),
}
#: Rejection messages every dialect names (the drive may append detail, e.g. the axis).
REJECTION_KEYS = ("unknown", "format", "property", "axis", "unsupported")
INFO_KEYS = frozenset({"hardware", "firmware", "serial_number"})
_TOP_KEYS = frozenset(
    {
        "dialect",
        "units",
        "commands",
        "extensions",
        "replies",
        "rejections",
        "states",
        "errors",
        "info",
    }
)
_DIALECT_KEYS = frozenset(
    {"name", "protocol", "firmware", "reference", "terminator", "reply_terminator", "checksum",
     "use_checksum", "float_format", "reply_float_format", "axis"}
)  # fmt: skip


@dataclass(frozen=True)
class ParsedLine:
    """A request or reply line matched against a template: which one, and its typed fields."""

    name: str
    fields: Mapping[str, int | float | str]


@dataclass(frozen=True)
class Dialect:
    """A parsed and validated dialect file (see ``drivers/data/dialects/odrive.toml``).

    Attributes
    ----------
    name, protocol, firmware, reference : str
        Identity: name, protocol and firmware it follows, documentation URL.
    source : str
        File it was read from.
    terminator, reply_terminator : bytes
        Line end the host appends to requests / the drive appends to replies.
    checksum : str
        Checksum the drive understands: ``"xor"`` or ``"none"``.
    use_checksum : bool
        Whether the host appends checksums unless the URL says otherwise.
    float_format, reply_float_format : str
        ``format()`` spec of floats in requests / in the served simulator's replies.
    axis : int
        Axis (motor) number used when the URL names none.
    units : Mapping[str, str]
        Units of command ``u``, velocity ``v`` and position ``x``.
    commands, replies, info : Mapping[str, Template]
        Request, reply and info-line templates by name.
    extensions : frozenset[str]
        Names in ``commands`` that are servobench extensions (from ``[extensions]``).
    rejections : Mapping[str, str]
        Rejection messages by key (:data:`REJECTION_KEYS`).
    states : Mapping[str, int]
        State codes ``enabled`` and ``disabled``.
    error_bits : Mapping[str, int]
        Error flag names -> bit values, for messages.
    watchdog_error, other_error : int
        Error codes the simulator reports for a watchdog trip / any other fault.
    """

    name: str
    source: str
    protocol: str
    firmware: str
    reference: str
    terminator: bytes
    reply_terminator: bytes
    checksum: str
    use_checksum: bool
    float_format: str
    reply_float_format: str
    axis: int
    units: Mapping[str, str]
    commands: Mapping[str, Template]
    replies: Mapping[str, Template]
    info: Mapping[str, Template]
    extensions: frozenset[str]
    rejections: Mapping[str, str]
    states: Mapping[str, int]
    error_bits: Mapping[str, int] = field(default_factory=dict)
    watchdog_error: int = 0
    other_error: int = 0

    def has(self, command: str) -> bool:
        return command in self.commands

    def request(self, command: str, **values: int | float | str) -> str:
        """Body of request ``command`` (no checksum, no terminator)."""
        if command not in self.commands:
            raise DriveConfigError(f"dialect {self.name!r} has no {command!r} command")
        return self.commands[command].format(self.float_format, **values)

    def reply(self, name: str, **values: int | float | str) -> str:
        """Body of reply ``name`` as the drive would write it (used by the simulator)."""
        return self.replies[name].format(self.reply_float_format, **values)

    def parse_reply(self, name: str, body: str) -> ParsedLine:
        """Fields of reply ``name``; :class:`MalformedReplyError` when ``body`` does not fit."""
        fields = self.replies[name].parse(body)
        if fields is None:
            raise MalformedReplyError(
                f"garbled {name} reply {body!r} (expected {self.replies[name].text!r})"
            )
        return ParsedLine(name, fields)

    def rejection(self, body: str) -> str | None:
        """The rejection key when ``body`` is one of the drive's refusal messages."""
        for key, text in self.rejections.items():
            if body == text or body.startswith(text + " "):
                return key
        return None

    def match_request(self, body: str) -> ParsedLine | None:
        """Which command ``body`` is, with its fields (used by the simulator); ``None`` if none."""
        for name, template in self.commands.items():
            fields = template.parse(body)
            if fields is not None:
                return ParsedLine(name, fields)
        return None

    def describe_error(self, code: int) -> str:
        """``"0x00000800 (WATCHDOG_TIMER_EXPIRED)"``: the code and the flags it holds."""
        names = [n for n, bit in self.error_bits.items() if bit and code & bit == bit]
        return f"0x{code:08X}" + (f" ({' | '.join(names)})" if names else "")


# ---------------------------------------------------------------- loading
def dialect_path(name_or_path: str) -> Path:
    """The file of a shipped dialect name, or ``name_or_path`` itself when it is a path."""
    if "/" in name_or_path or "\\" in name_or_path or name_or_path.endswith(".toml"):
        return Path(name_or_path)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name_or_path):
        raise DriveConfigError(f"not a dialect name or file: {name_or_path!r}")
    path = DIALECT_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in DIALECT_DIR.glob("*.toml"))) or "none"
        raise DriveConfigError(f"unknown serial dialect {name_or_path!r} (shipped: {known})")
    return path


def load_dialect(name_or_path: str = DEFAULT_DIALECT) -> Dialect:
    """Read, validate and compile a dialect (shipped name or TOML file path)."""
    path = dialect_path(name_or_path)
    return parse_dialect(read_toml(path, "dialect file"), str(path))


def _table(data: Mapping[str, object], key: str, where: str, required: bool = True) -> dict:
    if key not in data:
        if required:
            raise DriveConfigError(f"{where}: missing table [{key}]")
        return {}
    value = data[key]
    if not isinstance(value, dict):
        raise DriveConfigError(f"{where}: [{key}] must be a table")
    return value


def _no_unknown(
    table: Mapping[str, object], allowed: frozenset[str] | set[str], where: str
) -> None:
    unknown = sorted(set(table) - set(allowed))
    if unknown:
        raise DriveConfigError(
            f"{where}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(allowed))})"
        )


def _get(table: Mapping[str, object], key: str, kind: type, where: str, default: object = None):
    if key not in table:
        if default is None:
            raise DriveConfigError(f"{where}: missing key {key!r}")
        return default
    value = table[key]
    if kind is int and isinstance(value, bool) or not isinstance(value, kind):
        raise DriveConfigError(f"{where}: {key} must be a {kind.__name__}, got {value!r}")
    return value


def parse_dialect(data: Mapping[str, object], source: str = "<dialect>") -> Dialect:
    """Validate the TOML tables of a dialect and compile its templates.

    Raises
    ------
    DriveConfigError
        Naming ``source`` and the offending table and key: a missing or
        unknown key, a wrong type, a template with an unknown field, a reply
        template lacking a field.
    """
    w = f"dialect {source}"
    _no_unknown(data, _TOP_KEYS, w)
    meta = _table(data, "dialect", w)
    _no_unknown(meta, _DIALECT_KEYS, f"{w} [dialect]")
    wm = f"{w} [dialect]"
    checksum = _get(meta, "checksum", str, wm, "none")
    if checksum not in ("none", "xor"):
        raise DriveConfigError(f"{wm}: checksum must be 'none' or 'xor', got {checksum!r}")
    use_checksum = _get(meta, "use_checksum", bool, wm, False)
    if use_checksum and checksum == "none":
        raise DriveConfigError(f"{wm}: use_checksum = true needs checksum = 'xor'")
    float_formats = {}
    for key, default in (("float_format", ".7g"), ("reply_float_format", ".6f")):
        spec = _get(meta, key, str, wm, default)
        try:
            format(1.5, spec)
        except ValueError:
            raise DriveConfigError(f"{wm}: {key} {spec!r} is not a float format") from None
        float_formats[key] = spec
    terminators = {}
    for key, default in (("terminator", "\n"), ("reply_terminator", "\r\n")):
        term = _get(meta, key, str, wm, default)
        if term not in ("\n", "\r", "\r\n"):
            raise DriveConfigError(f"{wm}: {key} must be \\n, \\r or \\r\\n, got {term!r}")
        terminators[key] = term.encode("ascii")
    axis = _get(meta, "axis", int, wm, 0)

    units = _table(data, "units", w)
    _no_unknown(units, {"u", "v", "x"}, f"{w} [units]")
    units = {k: _get(units, k, str, f"{w} [units]") for k in ("u", "v", "x")}

    raw_commands = _table(data, "commands", w)
    raw_ext = _table(data, "extensions", w, required=False)
    _no_unknown(raw_commands, set(COMMAND_SPECS) - EXTENSION_COMMANDS, f"{w} [commands]")
    _no_unknown(raw_ext, EXTENSION_COMMANDS, f"{w} [extensions]")
    commands: dict[str, Template] = {}
    for table_name, table in (("commands", raw_commands), ("extensions", raw_ext)):
        for name, text in table.items():
            where = f"{w} [{table_name}] {name}"
            commands[name] = Template.compile(where, text, COMMAND_SPECS[name].fields)
    for name, spec in COMMAND_SPECS.items():
        if spec.required and name not in commands:
            raise DriveConfigError(f"{w} [commands]: missing key {name!r}")
    if ("set_cycle" in commands) != ("cycle_readback" in commands):
        raise DriveConfigError(f"{w} [extensions]: set_cycle and cycle_readback go together")

    raw_replies = _table(data, "replies", w)
    _no_unknown(raw_replies, set(REPLY_FIELDS), f"{w} [replies]")
    replies: dict[str, Template] = {}
    for name, text in raw_replies.items():
        where = f"{w} [replies] {name}"
        replies[name] = Template.compile(where, text, REPLY_FIELDS[name])
        lacking = REPLY_FIELDS[name] - set(replies[name].fields)
        if lacking:
            raise DriveConfigError(f"{where}: must hold field(s) {', '.join(sorted(lacking))}")
    for name in commands:
        reply = COMMAND_SPECS[name].reply
        if reply is not None and reply not in replies:
            raise DriveConfigError(f"{w} [replies]: missing key {reply!r} (reply of {name})")

    info: dict[str, Template] = {}
    raw_info = _table(data, "info", w, required="info" in commands)
    _no_unknown(raw_info, INFO_KEYS, f"{w} [info]")
    for name, text in raw_info.items():
        info[name] = Template.compile(f"{w} [info] {name}", text, frozenset({"text"}))

    raw_rej = _table(data, "rejections", w)
    _no_unknown(raw_rej, set(REJECTION_KEYS), f"{w} [rejections]")
    rejections = {k: _get(raw_rej, k, str, f"{w} [rejections]") for k in REJECTION_KEYS}

    raw_states = _table(data, "states", w)
    _no_unknown(raw_states, {"enabled", "disabled"}, f"{w} [states]")
    states = {k: _get(raw_states, k, int, f"{w} [states]") for k in ("enabled", "disabled")}
    if states["enabled"] == states["disabled"]:
        raise DriveConfigError(f"{w} [states]: enabled and disabled must differ")

    raw_err = _table(data, "errors", w)
    _no_unknown(raw_err, {"watchdog", "other", "bits"}, f"{w} [errors]")
    bits_table = _table(raw_err, "bits", f"{w} [errors]")
    bits = {k: _get(bits_table, k, int, f"{w} [errors.bits]") for k in bits_table}
    roles = {}
    for role in ("watchdog", "other"):
        flag = _get(raw_err, role, str, f"{w} [errors]")
        if flag not in bits or bits[flag] == 0:
            raise DriveConfigError(
                f"{w} [errors]: {role} = {flag!r} is not a flag in [errors.bits]"
            )
        roles[role] = bits[flag]

    return Dialect(
        name=_get(meta, "name", str, wm),
        source=source,
        protocol=_get(meta, "protocol", str, wm, ""),
        firmware=_get(meta, "firmware", str, wm, ""),
        reference=_get(meta, "reference", str, wm, ""),
        terminator=terminators["terminator"],
        reply_terminator=terminators["reply_terminator"],
        checksum=checksum,
        use_checksum=use_checksum,
        float_format=float_formats["float_format"],
        reply_float_format=float_formats["reply_float_format"],
        axis=axis,
        units=units,
        commands=commands,
        replies=replies,
        info=info,
        extensions=frozenset(raw_ext),
        rejections=rejections,
        states=states,
        error_bits=bits,
        watchdog_error=roles["watchdog"],
        other_error=roles["other"],
    )
