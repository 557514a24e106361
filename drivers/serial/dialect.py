"""Serial ASCII dialects: line-based drive protocols described by a TOML file.

A dialect names, for one family of drives, the text of every request the
serial backend sends (torque command, feedback query, enable, state and
error reads, watchdog set-up and feed, clear errors ...), the shape of the
replies, the line terminators and the checksum rule. Both sides use it: the
host (:mod:`servobench.drivers.serial.drive`) formats requests and parses replies, the
served simulator (:mod:`servobench.sim_backend.servers.serial.serve_serial`) parses requests and
formats replies, so the two agree by construction.

Everything here is pure: text in, text or frozen dataclasses out, no I/O.

Templates (``"c {axis} {u}"``) are :class:`servobench.drivers.serial.line_template.Template`;
line framing and checksums are in :mod:`servobench.drivers.serial.ascii_line`.

Firmware versions: ``[firmware] version`` lists the property reads that
give the drive's major, minor and revision numbers, and each
``[firmware.fallback.COMMAND]`` names a command whose requests differ on firmware
older than ``below`` (``[firmware.fallback.clear_errors]``: ODrive's ``sc``
exists from 0.5.2; before it, the error properties are written 0 one by one). ``[units.si]`` says how ``units=si``
converts the drive's own units (``x = {unit = "rad", factor = 6.283...}``:
SI value = drive value * factor).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from servobench.drivers.serial.ascii_line import MalformedReplyError
from servobench.drivers.serial.line_template import Template
from servobench.errors import DriveConfigError, DriveError
from servobench.tomlfile import SENTENCE, TomlTable, read_toml

#: Folder of the shipped dialects (``dialect=NAME`` means ``NAME.toml`` here).
DIALECT_DIR = Path(__file__).parents[1] / "data" / "dialects"
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
    "watchdog_disable": CommandSpec(frozenset({"axis"}), required=False),
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
        "firmware",
    }
)
_STATE_KEYS = ("enabled", "disabled")
_DIALECT_KEYS = frozenset(
    {"name", "protocol", "firmware", "reference", "terminator", "reply_terminator", "checksum",
     "use_checksum", "float_format", "reply_float_format", "axis", "line_ends", "firmware_model"}
)  # fmt: skip
#: Firmware models the served simulator can emulate (``[dialect] firmware_model``).
FIRMWARE_MODELS = ("", "odrive-0.5")


@dataclass(frozen=True)
class Fallback:
    """Requests that replace ``command`` on firmware older than ``below`` (major, minor, revision)."""

    command: str
    below: tuple[int, ...]
    requests: tuple[Template, ...]


def parse_version(text: str) -> tuple[int, ...]:
    """``"0.5.2"`` -> ``(0, 5, 2)``; :class:`DriveConfigError` for anything else."""
    try:
        parts = tuple(int(p) for p in text.strip().lstrip("v").split("."))
    except ValueError:
        raise DriveConfigError(f"not a firmware version: {text!r} (expected e.g. 0.5.6)") from None
    if not parts or any(p < 0 for p in parts):
        raise DriveConfigError(f"not a firmware version: {text!r} (expected e.g. 0.5.6)")
    return parts


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
    line_ends : bytes
        Bytes that end a request line at the drive (ODrive: ``\\r``, ``\\n`` and ``!``).
    firmware_model : str
        Firmware the served simulator emulates (:data:`FIRMWARE_MODELS`; ``""``: generic).
    version_requests : tuple of str
        Reads giving the firmware's major, minor, revision (empty: not readable).
    fallbacks : tuple of Fallback
        Commands that differ on older firmware.
    si_units : Mapping[str, tuple[str, float]]
        Signal -> (SI unit, factor) for ``units=si``.
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
    line_ends: bytes = b"\r\n"
    firmware_model: str = ""
    version_requests: tuple[str, ...] = ()
    fallbacks: tuple[Fallback, ...] = ()
    si_units: Mapping[str, tuple[str, float]] = field(default_factory=dict)

    def has(self, command: str) -> bool:
        return command in self.commands

    def requests(
        self, command: str, firmware: tuple[int, ...] | None = None, **values: int | float | str
    ) -> list[str]:
        """Bodies of ``command`` for a drive at ``firmware`` (None: unknown, the stock request)."""
        for fb in self.fallbacks:
            if fb.command == command and firmware is not None and firmware < fb.below:
                return [t.format(self.float_format, **values) for t in fb.requests]
        return [self.request(command, **values)]

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
def shipped_dialects() -> list[str]:
    """Names of the dialects shipped in ``drivers/data/dialects``."""
    return sorted(p.stem for p in DIALECT_DIR.glob("*.toml"))


def dialect_path(name_or_path: str) -> Path:
    """The file of a shipped dialect name, or ``name_or_path`` itself when it is a path."""
    if "/" in name_or_path or "\\" in name_or_path or name_or_path.endswith(".toml"):
        return Path(name_or_path)
    if not re.fullmatch(r"[A-Za-z0-9_.-]+", name_or_path):
        raise DriveConfigError(f"not a dialect name or file: {name_or_path!r}")
    path = DIALECT_DIR / f"{name_or_path}.toml"
    if not path.is_file():
        known = ", ".join(shipped_dialects()) or "none"
        raise DriveConfigError(f"unknown serial dialect {name_or_path!r} (shipped: {known})")
    return path


def load_dialect(name_or_path: str = DEFAULT_DIALECT) -> Dialect:
    """Read, validate and compile a dialect (shipped name or TOML file path)."""
    path = dialect_path(name_or_path)
    return parse_dialect(read_toml(path, "dialect file"), str(path))


def _templates(t: TomlTable, fields: Mapping[str, frozenset[str]]) -> dict[str, Template]:
    """The templates of table ``t`` by name; ``fields`` maps every allowed name to its fields."""
    return {
        name: Template.compile(f"{t.where} {name}", t.get(name, object), fields[name])
        for name in t.allow(fields)
    }


def _command_fields(extensions: bool) -> dict[str, frozenset[str]]:
    """Fields of the commands of ``[extensions]`` (or of ``[commands]``)."""
    return {
        n: s.fields for n, s in COMMAND_SPECS.items() if (n in EXTENSION_COMMANDS) == extensions
    }


def _read_meta(meta: TomlTable) -> dict[str, object]:
    """The fields of :class:`Dialect` given by the ``[dialect]`` table."""
    meta.allow(_DIALECT_KEYS)
    fields: dict[str, object] = {
        "name": meta.get("name", str),
        **{k: meta.get(k, str, "") for k in ("protocol", "firmware", "reference")},
        "checksum": meta.choice("checksum", ("none", "xor"), "none"),
        "use_checksum": meta.get("use_checksum", bool, False),
        "axis": meta.get("axis", int, 0),
    }
    if fields["use_checksum"] and fields["checksum"] == "none":
        raise meta.table_error("use_checksum = true needs checksum = 'xor'")
    for key, default in (("float_format", ".7g"), ("reply_float_format", ".6f")):
        spec = fields[key] = meta.get(key, str, default)
        try:
            format(1.5, spec)
        except ValueError:
            raise meta.table_error(f"{key} {spec!r} is not a float format") from None
    for key, default in (("terminator", "\n"), ("reply_terminator", "\r\n")):
        fields[key] = meta.choice(key, ("\n", "\r", "\r\n"), default).encode("ascii")
    line_ends = meta.get("line_ends", str, "\r\n")
    if not line_ends or any(c not in "\r\n!" for c in line_ends) or "\n" not in line_ends:
        raise meta.error("line_ends", f"{line_ends!r} must hold \\n and only \\r, \\n or !")
    fields["line_ends"] = line_ends.encode("ascii")
    fields["firmware_model"] = meta.choice("firmware_model", FIRMWARE_MODELS, "")
    return fields


def _read_commands(top: TomlTable) -> tuple[dict[str, Template], frozenset[str]]:
    """Request templates of ``[commands]`` and ``[extensions]``; the names of the extensions."""
    stock = top.table("commands")
    ext = top.table("extensions", required=False)
    commands = {
        **_templates(stock, _command_fields(False)),
        **_templates(ext, _command_fields(True)),
    }
    stock.require(name for name, spec in COMMAND_SPECS.items() if spec.required)
    if ("set_cycle" in commands) != ("cycle_readback" in commands):
        raise ext.table_error("set_cycle and cycle_readback go together")
    return commands, frozenset(ext.data)


def _read_replies(top: TomlTable, commands: Mapping[str, Template]) -> dict[str, Template]:
    """Reply templates of ``[replies]``: each with all its fields, one for every command."""
    t = top.table("replies")
    replies = _templates(t, REPLY_FIELDS)
    for name, template in replies.items():
        lacking = REPLY_FIELDS[name] - set(template.fields)
        if lacking:
            raise t.error(name, f"must hold field(s) {', '.join(sorted(lacking))}")
    for name in commands:
        reply = COMMAND_SPECS[name].reply
        if reply is not None and reply not in replies:
            raise t.table_error(f"missing key {reply!r} (reply of {name})")
    return replies


def _read_texts(top: TomlTable, name: str, keys: Sequence[str]) -> dict[str, str]:
    """The table ``name``: the strings ``keys``, all of them and no other."""
    t = top.table(name)
    t.allow(keys)
    return {k: t.get(k, str) for k in keys}


def _read_states(top: TomlTable) -> dict[str, int]:
    """The state codes of ``[states]``: ``enabled`` and ``disabled``, different."""
    t = top.table("states")
    t.allow(_STATE_KEYS)
    states = {k: t.get(k, int) for k in _STATE_KEYS}
    if states["enabled"] == states["disabled"]:
        raise t.table_error("enabled and disabled must differ")
    return states


def _read_units(top: TomlTable) -> tuple[dict[str, str], dict[str, tuple[str, float]]]:
    """``[units]``: u, v, x; and ``[units.si]``: the SI unit and factor of each convertible one."""
    t = top.table("units")
    t.allow(("u", "v", "x", "si"))
    units = {k: t.get(k, str) for k in ("u", "v", "x")}
    si_table = t.table("si", required=False)
    si: dict[str, tuple[str, float]] = {}
    for key in si_table.allow(("v", "x"), noun="signal"):
        entry = si_table.table(key)
        unit, factor = entry.get("unit", str), entry.number("factor")
        entry.done()
        if not factor > 0:
            raise entry.error("factor", f"{factor!r} must be > 0")
        si[key] = (unit, float(factor))
    return units, si


def _read_firmware(top: TomlTable) -> tuple[tuple[str, ...], tuple[Fallback, ...]]:
    """``[firmware]``: the version reads and the fallbacks of older firmware."""
    t = top.table("firmware", required=False)
    version = t.sequence("version", str, ())
    if version and len(version) != 3:
        raise t.error("version", "must list 3 reads: major, minor, revision")
    table = t.table("fallback", required=False)
    fallbacks = []
    for command in table.allow(tuple(COMMAND_SPECS), noun="command"):
        fb = table.table(command)
        below = parse_version(fb.get("below", str))
        fields = COMMAND_SPECS[command].fields
        requests = tuple(
            Template.compile(f"{fb.where} requests", text, fields)
            for text in fb.sequence("requests", str)
        )
        if not requests:
            raise fb.error("requests", "must not be empty")
        fb.done()
        fallbacks.append(Fallback(command, below, requests))
    t.done()
    return version, tuple(fallbacks)


def _read_errors(top: TomlTable) -> tuple[dict[str, int], int, int]:
    """Error flags of ``[errors.bits]``; the codes of a watchdog trip and of any other fault."""
    t = top.table("errors")
    t.allow(("watchdog", "other", "bits"))
    flags = t.table("bits")
    bits = {k: flags.get(k, int) for k in flags.data}
    codes = []
    for role in ("watchdog", "other"):
        flag = t.get(role, str)
        if flag not in bits or bits[flag] == 0:
            raise t.table_error(f"{role} = {flag!r} is not a flag in [errors.bits]")
        codes.append(bits[flag])
    return bits, codes[0], codes[1]


def parse_dialect(data: Mapping[str, object], source: str = "<dialect>") -> Dialect:
    """Validate the TOML tables of a dialect and compile its templates.

    Raises
    ------
    DriveConfigError
        Naming ``source`` and the offending table and key: a missing or
        unknown key, a wrong type, a template with an unknown field, a reply
        template lacking a field.
    """
    top = TomlTable(data, f"dialect {source}", wording=SENTENCE)
    top.allow(_TOP_KEYS)
    meta = _read_meta(top.table("dialect"))
    units, si_units = _read_units(top)
    commands, extensions = _read_commands(top)
    replies = _read_replies(top, commands)
    info_table = top.table("info", required="info" in commands)
    info = _templates(info_table, dict.fromkeys(INFO_KEYS, frozenset({"text"})))
    rejections = _read_texts(top, "rejections", REJECTION_KEYS)
    states = _read_states(top)
    bits, watchdog_error, other_error = _read_errors(top)
    version_requests, fallbacks = _read_firmware(top)
    return Dialect(
        si_units=si_units,
        version_requests=version_requests,
        fallbacks=fallbacks,
        source=source,
        units=units,
        commands=commands,
        replies=replies,
        info=info,
        extensions=extensions,
        rejections=rejections,
        states=states,
        error_bits=bits,
        watchdog_error=watchdog_error,
        other_error=other_error,
        **meta,  # type: ignore[arg-type]
    )
