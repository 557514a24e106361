"""Modbus register maps: a TOML file that says where a drive keeps what.

A map names the registers a servo drive exposes for cyclic control
(``command``, ``velocity``, ``position``, ``fault``, ``control``,
``watchdog``; optionally ``status``, ``timestamp``, ``cycle``,
``watchdog_feed`` and the identity strings) with their address, format,
scale, word and byte order, register type and access. Both sides read the
same file: :mod:`servobench.drivers.modbus.drive` (the client) and
:mod:`servobench.sim_backend.servers.modbus.serve_modbus` (the served simulated drive), so they agree by
construction. This module is pure: parsing, validation and the codec, no I/O
beyond reading the file.

Value convention: ``physical = raw * scale``. Multi-register values are
packed big-endian, split into 16-bit words high word first, then reordered::

    int32 0x11223344, word_order="big",    byte_order="big"    -> [0x1122, 0x3344]
    int32 0x11223344, word_order="little", byte_order="big"    -> [0x3344, 0x1122]
    int32 0x11223344, word_order="big",    byte_order="little" -> [0x2211, 0x4433]

The TOML layout is documented in ``drivers/data/maps/servobench-sim.toml``.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from servobench.errors import DriveConfigError, UsageError
from servobench.tomlfile import NO_DEFAULT, TomlTable, read_toml

#: format -> (struct code, registers); "string" takes its count from the map.
FORMATS: dict[str, tuple[str, int]] = {
    "int16": ("h", 1),
    "uint16": ("H", 1),
    "int32": ("i", 2),
    "uint32": ("I", 2),
    "float32": ("f", 2),
    "string": ("s", 0),
}
#: Registers the host writes, and which of them a map must have.
WRITTEN = ("command", "control", "watchdog", "cycle", "watchdog_feed")
#: Registers read every cycle (the feedback blocks).
FEEDBACK = ("velocity", "position", "fault", "status", "timestamp")
IDENTITY = ("vendor", "product", "firmware", "serial_number")
REQUIRED = ("command", "velocity", "position", "fault", "control", "watchdog")
KNOWN_REGISTERS = frozenset(WRITTEN + FEEDBACK + IDENTITY)
#: Largest read of one Modbus request (FC3/FC4/FC23) [registers].
MAX_READ = 125
WATCHDOG_FEEDS = ("any_request", "register")
#: Registers whose scaled value is a time: their unit, when given, must be seconds.
TIMES = ("watchdog", "cycle", "timestamp")
#: ``fc23`` values: the drive has FC23, has not, or it is tried and dropped on exception 1.
FC23_AUTO = "auto"
_ORDERS = ("big", "little")


@dataclass(frozen=True)
class Register:
    """One value in the drive's register space.

    Attributes
    ----------
    name : str
        Role of the value (``"command"``, ``"velocity"`` ...).
    address : int
        First register, 0-based protocol address.
    format : str
        One of :data:`FORMATS`.
    count : int
        Registers occupied.
    scale : float
        Physical units per raw count (``physical = raw * scale``).
    word_order, byte_order : str
        ``"big"`` or ``"little"``; see the module docstring.
    kind : str
        ``"holding"`` or ``"input"`` register.
    access : str
        ``"r"``, ``"w"`` or ``"rw"``.
    unit : str
        Unit of the scaled value (``raw * scale``): an SI spelling of
        :mod:`servobench.units` (``"N m"``, ``"rad/s"``, ``"A"``, ``"s"`` ...) or
        the drive's own unit named as such (``"inc"``); ``""`` when the map does not say.
    """

    name: str
    address: int
    format: str
    count: int
    scale: float = 1.0
    word_order: str = "big"
    byte_order: str = "big"
    kind: str = "holding"
    access: str = "rw"
    unit: str = ""

    @property
    def end(self) -> int:
        """One past the last register."""
        return self.address + self.count


@dataclass(frozen=True)
class Block:
    """Registers read together in one request: ``count`` words from ``address``."""

    kind: str
    address: int
    count: int
    names: tuple[str, ...]


@dataclass(frozen=True)
class ControlWords:
    """Values written to the ``control`` register, in order, for each action."""

    enable: tuple[int, ...]
    disable: tuple[int, ...]
    quick_stop: tuple[int, ...] = ()
    reset_fault: tuple[int, ...] = ()


@dataclass(frozen=True)
class StatusBits:
    """Masks of the ``status`` register (``None``: the drive does not report it)."""

    enabled: int | None = None
    quick_stop: int | None = None
    fault: int | None = None


@dataclass(frozen=True)
class SetupWrite:
    """A raw register write done once when the drive is opened (mode selection ...)."""

    address: int
    value: int
    note: str = ""


@dataclass(frozen=True)
class RegisterMap:
    """A validated register map; see the module docstring."""

    name: str
    path: str
    registers: Mapping[str, Register]
    control: ControlWords
    status: StatusBits = StatusBits()
    fc23: bool = False
    fc23_auto: bool = False
    turnaround_s: float = 0.0
    watchdog_feed: str = "any_request"
    setup: tuple[SetupWrite, ...] = ()
    units: Mapping[str, str] = field(default_factory=dict)
    description: str = ""
    source: str = ""
    blocks: tuple[Block, ...] = ()

    def __getitem__(self, name: str) -> Register:
        return self.registers[name]

    def __contains__(self, name: object) -> bool:
        return name in self.registers

    @property
    def feedback(self) -> Block:
        """The block holding ``velocity``: read (or FC23-read) every cycle, first."""
        return self.blocks[0]

    @property
    def signal_units(self) -> dict[str, str]:
        """Units of command ``u``, velocity ``v``, position ``x``: the registers' own, else ``[units]``."""
        return {
            key: self.registers[name].unit or self.units.get(key, "")
            for key, name in (("u", "command"), ("v", "velocity"), ("x", "position"))
        }


# ---------------------------------------------------------------- codec
def _check_words(reg: Register, words: Sequence[int]) -> None:
    if len(words) != reg.count:
        raise UsageError(f"register {reg.name!r} takes {reg.count} word(s), got {len(words)}")
    for w in words:
        if not 0 <= w <= 0xFFFF:
            raise UsageError(f"register {reg.name!r}: word {w!r} is not 16-bit")


def _bytes_to_words(data: bytes, reg: Register) -> list[int]:
    words = [int.from_bytes(data[i : i + 2], "big") for i in range(0, len(data), 2)]
    if reg.word_order == "little":
        words.reverse()
    if reg.byte_order == "little":
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    return words


def _words_to_bytes(words: Sequence[int], reg: Register) -> bytes:
    words = list(words)
    if reg.byte_order == "little":
        words = [((w & 0xFF) << 8) | (w >> 8) for w in words]
    if reg.word_order == "little":
        words.reverse()
    return b"".join(w.to_bytes(2, "big") for w in words)


def encode_raw(reg: Register, raw: int | float) -> list[int]:
    """Words holding the raw value ``raw`` (no scaling); range-checked."""
    code, _ = FORMATS[reg.format]
    try:
        data = struct.pack(f">{code}", raw)
    except (struct.error, OverflowError) as err:
        raise UsageError(
            f"register {reg.name!r}: raw value {raw!r} does not fit {reg.format}"
        ) from err
    return _bytes_to_words(data, reg)


def decode_raw(reg: Register, words: Sequence[int]) -> int | float:
    """Raw value held in ``words`` (no scaling)."""
    _check_words(reg, words)
    code, _ = FORMATS[reg.format]
    return struct.unpack(f">{code}", _words_to_bytes(words, reg))[0]


def encode(reg: Register, value: float) -> list[int]:
    """Words for the physical ``value`` (``raw = value / scale``, rounded for integers).

    Raises
    ------
    UsageError
        ``value`` is not finite or does not fit the register.
    """
    if not math.isfinite(value):
        raise UsageError(f"register {reg.name!r}: value {value!r} is not finite")
    raw = value / reg.scale
    if reg.format != "float32":
        raw = int(round(raw))
    return encode_raw(reg, raw)


def decode(reg: Register, words: Sequence[int]) -> float:
    """Physical value held in ``words`` (``raw * scale``)."""
    return float(decode_raw(reg, words)) * reg.scale


def encode_string(reg: Register, text: str) -> list[int]:
    """Words of an ASCII/UTF-8 string register, NUL-padded to its size."""
    data = text.encode()
    if len(data) > 2 * reg.count:
        raise UsageError(f"register {reg.name!r}: {text!r} longer than {2 * reg.count} bytes")
    return _bytes_to_words(data.ljust(2 * reg.count, b"\0"), reg)


def decode_string(reg: Register, words: Sequence[int]) -> str:
    """Text of a string register, trailing NULs and blanks removed."""
    _check_words(reg, words)
    return _words_to_bytes(words, reg).rstrip(b"\0 ").decode(errors="replace")


def words_of(block: Block, reg: Register, words: Sequence[int]) -> list[int]:
    """The words of ``reg`` inside the words read for ``block``."""
    offset = reg.address - block.address
    return list(words[offset : offset + reg.count])


# -------------------------------------------------------------- parsing
def shipped_maps() -> list[str]:
    """Names of the maps shipped in ``drivers/data/maps``."""
    folder = resources.files("servobench.drivers") / "data" / "maps"
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".toml"))


def resolve_map(name_or_path: str) -> Path:
    """The file of a shipped map name, or ``name_or_path`` itself when it is a path."""
    if name_or_path.endswith(".toml") or "/" in name_or_path or "\\" in name_or_path:
        path = Path(name_or_path)
        if not path.is_file():
            raise DriveConfigError(f"register map file {name_or_path!r} does not exist")
        return path
    if name_or_path not in shipped_maps():
        raise DriveConfigError(
            f"unknown register map {name_or_path!r}; shipped: {', '.join(shipped_maps())} "
            "(or give a path to a .toml file)"
        )
    return Path(str(resources.files("servobench.drivers") / "data" / "maps" / f"{name_or_path}.toml"))


def load_map(name_or_path: str) -> RegisterMap:
    """Read and validate a register map (a shipped name or a TOML path)."""
    path = resolve_map(name_or_path)
    return parse_map(read_toml(path, "register map file"), str(path))


def _words(t: TomlTable, key: str, default: object = NO_DEFAULT) -> tuple[int, ...]:
    """The list ``key`` of 16-bit unsigned words (control values)."""
    words = t.sequence(key, int, default)
    if not all(0 <= w <= 0xFFFF for w in words):
        raise t.error(key, f"{list(words)!r} must be a list of 16-bit unsigned integers")
    return tuple(words)


def _parse_register(name: str, t: TomlTable, orders: tuple[str, str]) -> Register:
    """Register ``name`` from its table; ``orders`` are the map's word and byte order."""
    address = t.get("address", int)
    if not 0 <= address <= 0xFFFF:
        raise t.error("address", f"{address} is outside 0..65535")
    fmt = t.choice("format", tuple(FORMATS), "uint16")
    count = FORMATS[fmt][1]
    if fmt == "string":
        count = t.get("count", int)
        if not 1 <= count <= MAX_READ:
            raise t.error("count", f"{count} is outside 1..{MAX_READ}")
    if address + count > 0x10000:
        raise t.error("address", "register runs past address 65535")
    scale = t.get("scale", float, 1.0)
    if not (math.isfinite(scale) and scale != 0):
        raise t.error("scale", f"{scale!r} must be a finite non-zero number")
    if fmt == "string" and scale != 1.0:
        raise t.error("scale", "a string register takes no scale")
    reg = Register(
        name=name,
        address=address,
        format=fmt,
        count=count,
        scale=float(scale),
        word_order=t.choice("word_order", _ORDERS, orders[0]),
        byte_order=t.choice("byte_order", _ORDERS, orders[1]),
        kind=t.choice("type", ("holding", "input"), "holding"),
        access=t.choice("access", ("r", "w", "rw"), "r" if name in FEEDBACK + IDENTITY else "rw"),
        unit=t.get("unit", str, "").strip(),
    )
    t.done()
    if reg.unit and (fmt == "string" or name in ("control", "fault", "status", "watchdog_feed")):
        raise t.error("unit", "only scaled values take a unit")
    if reg.unit and name in TIMES and reg.unit != "s":
        raise t.error("unit", f"{reg.unit!r}: the host reads and writes this register in s")
    if name in WRITTEN and (reg.kind != "holding" or "w" not in reg.access):
        raise t.error(
            "access", "the host writes this register: it must be a writable holding register"
        )
    if name in FEEDBACK + IDENTITY and "r" not in reg.access:
        raise t.error("access", "the host reads this register: it must be readable")
    if name in IDENTITY and fmt not in ("string", "uint16", "uint32"):
        raise t.error("format", "identity registers are strings or unsigned integers")
    return reg


def _feedback_blocks(regs: Mapping[str, Register], max_gap: int) -> tuple[Block, ...]:
    """Group the feedback registers into as few reads as the gaps allow, velocity's first."""
    members = sorted(
        (r for n, r in regs.items() if n in FEEDBACK), key=lambda r: (r.kind, r.address)
    )
    groups: list[list[Register]] = []
    for reg in members:
        last = groups[-1] if groups else None
        if (
            last
            and last[-1].kind == reg.kind
            and reg.address - max(r.end for r in last) <= max_gap
            and reg.end - last[0].address <= MAX_READ
        ):
            last.append(reg)
        else:
            groups.append([reg])
    blocks = [
        Block(
            g[0].kind, g[0].address, max(r.end for r in g) - g[0].address, tuple(r.name for r in g)
        )
        for g in groups
    ]
    blocks.sort(key=lambda b: "velocity" not in b.names)
    return tuple(blocks)


def _parse_registers(top: TomlTable, orders: tuple[str, str]) -> dict[str, Register]:
    """The ``[registers.NAME]`` tables: known names, the required ones, none overlapping."""
    table = top.table("registers")
    regs = {
        name: _parse_register(name, table.table(name), orders)
        for name in table.allow(KNOWN_REGISTERS, noun="register")
    }
    table.require(REQUIRED)
    ordered = sorted(regs.values(), key=lambda r: (r.kind, r.address))
    for a, b in zip(ordered, ordered[1:], strict=False):
        if a.kind == b.kind and b.address < a.end:
            raise table.error(b.name, f"overlaps register {a.name!r} at address {b.address:#06x}")
    return regs


def _parse_control(top: TomlTable) -> ControlWords:
    t = top.table("control")
    control = ControlWords(
        enable=_words(t, "enable"),
        disable=_words(t, "disable"),
        quick_stop=_words(t, "quick_stop", []),
        reset_fault=_words(t, "reset_fault", []),
    )
    t.done()
    if not control.enable or not control.disable:
        raise t.error("enable" if not control.enable else "disable", "must not be empty")
    return control


def _parse_status(top: TomlTable, regs: Mapping[str, Register]) -> StatusBits:
    t = top.table("status", required=False)
    status = StatusBits(
        *(t.get(k, int, None) for k in ("enabled_mask", "quick_stop_mask", "fault_mask"))
    )
    t.done()
    masks = (status.enabled, status.quick_stop, status.fault)
    if any(m is not None for m in masks) and "status" not in regs:
        raise t.error("enabled_mask", "status masks need a [registers.status] entry")
    return status


def _parse_watchdog(top: TomlTable, regs: Mapping[str, Register]) -> str:
    t = top.table("watchdog", required=False)
    feed = t.choice("feed", WATCHDOG_FEEDS, "any_request")
    t.done()
    if feed == "register" and "watchdog_feed" not in regs:
        raise t.error("feed", "'register' needs a [registers.watchdog_feed] entry")
    return feed


def _parse_setup(top: TomlTable) -> tuple[SetupWrite, ...]:
    setup = []
    for s in top.tables("setup", []):
        address, value = s.get("address", int), s.get("value", int)
        if not (0 <= address <= 0xFFFF and 0 <= value <= 0xFFFF):
            raise s.error("value", "address and value must be 16-bit unsigned integers")
        setup.append(SetupWrite(address, value, s.get("note", str, "")))
        s.done()
    return tuple(setup)


def _parse_units(top: TomlTable, regs: Mapping[str, Register]) -> dict[str, str]:
    """``[units]``: units of u, v, x for registers that name none; where both say, they agree."""
    t = top.table("units", required=False)
    units = {k: t.get(k, str, "") for k in ("u", "v", "x")}
    t.done()
    for key, name in (("u", "command"), ("v", "velocity"), ("x", "position")):
        own = regs[name].unit
        if own and units[key] and own != units[key]:
            raise t.error(key, f"{units[key]!r} contradicts [registers.{name}] unit {own!r}")
    return units


def _parse_fc23(head: TomlTable) -> tuple[bool, bool]:
    """``fc23``: true, false or "auto" -> (try FC23 first, drop it on exception 1)."""
    value = head.get("fc23", object, False)
    if value == FC23_AUTO:
        return True, True
    if not isinstance(value, bool):
        raise head.error("fc23", f"expected bool, got {value!r} (or {FC23_AUTO!r})")
    return value, False


def parse_map(doc: Mapping[str, object], path: str = "<map>") -> RegisterMap:
    """Validate a parsed TOML document; every malformed entry names file, table and key."""
    top = TomlTable(doc, path)
    head = top.table("map")
    name = head.get("name", str)
    description = head.get("description", str, "")
    source = head.get("source", str, "")
    fc23, fc23_auto = _parse_fc23(head)
    turnaround_ms = head.number("turnaround_ms", 0.0)
    if turnaround_ms < 0:
        raise head.error("turnaround_ms", f"{turnaround_ms} must be >= 0")
    orders = (head.choice("word_order", _ORDERS, "big"), head.choice("byte_order", _ORDERS, "big"))
    max_gap = head.get("max_gap", int, 0)
    if not 0 <= max_gap < MAX_READ:
        raise head.error("max_gap", f"{max_gap} is outside 0..{MAX_READ - 1}")
    head.done()

    regs = _parse_registers(top, orders)
    blocks = _feedback_blocks(regs, max_gap)
    regmap = RegisterMap(
        name=name,
        path=path,
        registers=regs,
        control=_parse_control(top),
        status=_parse_status(top, regs),
        fc23=fc23,
        fc23_auto=fc23_auto,
        turnaround_s=turnaround_ms / 1000.0,
        watchdog_feed=_parse_watchdog(top, regs),
        setup=_parse_setup(top),
        units=_parse_units(top, regs),
        description=description,
        source=source,
        blocks=blocks,
    )
    top.done()
    if fc23 and blocks[0].kind != "holding":
        raise head.error(
            "fc23", "FC23 reads holding registers; the velocity block is input registers"
        )
    return regmap
