"""The bench's udev rules: find, render and install them; match USB devices.

The rule files ship as templates in the ``servobench.udev`` package (the
``udev/`` folder of a checkout), found through :mod:`importlib.resources`. A
template holds ``@GROUP@``, ``@BITRATE@`` [bit/s] and ``@RESTART_MS@`` [ms]
and one marker line ``# @CAN_NAMES@`` that :func:`render` replaces with the
``NAME=`` rules of the SocketCAN interfaces. :mod:`servobench.udev.lint` checks
them before anything is written.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from importlib import resources
from pathlib import Path

from servobench.errors import ServobenchError, UsageError
from servobench.udev.lint import IFNAMSIZ, LintResult, lint_text

CAN_NAMES_MARKER = "# @CAN_NAMES@"
RULES_SUBDIR = Path("etc/udev/rules.d")
MAX_CAN_BITRATE = 1_000_000  # classic CAN [bit/s]


# ----------------------------------------------------------------- finding
def rules_dir() -> Path:
    """The folder of the shipped rule templates: the files of the ``servobench.udev`` package."""
    folder = Path(str(resources.files("servobench.udev")))
    if not any(folder.glob("*.rules")):
        raise ServobenchError(f"udev rules not found in {folder}: reinstall servobench")
    return folder


def shipped_rules() -> tuple[Path, ...]:
    """The shipped rule templates, sorted by name (the order udev reads them)."""
    return tuple(sorted(rules_dir().glob("*.rules")))


# ----------------------------------------------------------------- rendering
@dataclass(frozen=True)
class CanName:
    """A fixed SocketCAN interface name for the adapter with a USB serial or path."""

    name: str
    selector: str  # "serial" or "path"
    value: str

    def rule(self) -> str:
        match = (
            f'ATTRS{{serial}}=="{self.value}"'
            if self.selector == "serial"
            else f'ENV{{ID_PATH}}=="{self.value}"'
        )
        return f'{match}, NAME="{self.name}"'


def parse_can_name(spec: str) -> CanName:
    """Parse ``NAME=serial:SERIAL`` or ``NAME=path:ID_PATH`` (``udevadm info`` shows both)."""
    name, _, sel = spec.partition("=")
    selector, _, value = sel.partition(":")
    if not re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]{0,14}", name):
        raise UsageError(
            f"--can-name {spec!r}: NAME must be 1-{IFNAMSIZ} letters, digits, '_' or '-'"
        )
    if selector not in ("serial", "path") or not re.fullmatch(r"[A-Za-z0-9._:+-]+", value):
        raise UsageError(f"--can-name {spec!r}: expected NAME=serial:SERIAL or NAME=path:ID_PATH")
    return CanName(name, selector, value)


@dataclass(frozen=True)
class InstallOptions:
    """What the installer fills into the templates."""

    bitrate: int = 1_000_000  # [bit/s]
    restart_ms: int = 100  # bus-off auto-restart delay [ms]
    group: str = "plugdev"
    can_names: tuple[CanName, ...] = field(default=())

    def __post_init__(self) -> None:
        if not 0 < self.bitrate <= MAX_CAN_BITRATE:
            raise UsageError(f"bitrate {self.bitrate} bit/s is outside 1..{MAX_CAN_BITRATE}")
        if not 0 < self.restart_ms <= 60_000:
            raise UsageError(f"restart-ms {self.restart_ms} is outside 1..60000 ms")
        if not re.fullmatch(r"[a-z_][a-z0-9_-]{0,31}", self.group):
            raise UsageError(f"group {self.group!r} is not a valid group name")
        names = [c.name for c in self.can_names]
        if len(set(names)) != len(names):
            raise UsageError("--can-name: each interface name may be given once")


def render(text: str, options: InstallOptions) -> str:
    """Fill a template: variables, and the CAN names at the marker line.

    Without ``can_names`` every bench CAN interface is named ``servocan<N>``
    after its kernel number (``can0`` -> ``servocan0``); with them only the
    listed adapters are renamed, so that no name is taken twice.
    """
    names = [c.rule() for c in options.can_names] or ['NAME=="", NAME="servocan%n"']
    lines = []
    for line in text.splitlines():
        if line.strip() == CAN_NAMES_MARKER:
            lines += ["# fixed interface names (servobench udev install --can-name)", *names]
        else:
            lines.append(
                line.replace("@GROUP@", options.group)
                .replace("@BITRATE@", str(options.bitrate))
                .replace("@RESTART_MS@", str(options.restart_ms))
            )
    return "\n".join(lines) + "\n"


@dataclass(frozen=True)
class InstallResult:
    """Where the rendered rule files went."""

    target: Path
    files: tuple[Path, ...]


def install(
    root: Path, options: InstallOptions, sources: Iterable[Path] | None = None
) -> InstallResult:
    """Render the rule templates and write them to ``root/etc/udev/rules.d``.

    Every file is rendered and linted before the first one is written; each
    is written to a temporary file and renamed into place.

    Raises
    ------
    UsageError
        The target folder cannot be created or written, or a rendered file
        does not lint clean.
    """
    sources = tuple(sources) if sources is not None else shipped_rules()
    rendered = {}
    for src in sources:
        text = render(src.read_text(encoding="utf-8"), options)
        bad = lint_text(text, src.name).errors
        if bad:
            raise UsageError(f"rendered rules do not lint clean: {bad[0]}")
        rendered[src.name] = text
    target = Path(root) / RULES_SUBDIR
    written = []
    try:
        target.mkdir(parents=True, exist_ok=True)
        for name, text in rendered.items():
            tmp = target / f".{name}.tmp"
            tmp.write_text(text, encoding="utf-8")
            tmp.chmod(0o644)
            os.replace(tmp, target / name)
            written.append(target / name)
    except OSError as err:
        hint = " (run as root, or give --root DIR)" if isinstance(err, PermissionError) else ""
        raise UsageError(
            f"cannot write udev rules to {target}: {err.strerror or err}{hint}"
        ) from err
    return InstallResult(target, tuple(written))


# ----------------------------------------------------------------- devices
@dataclass(frozen=True)
class UsbMatch:
    """A vendor/product pattern pair some rule matches on (udev glob, '|' alternatives)."""

    vendor: str
    product: str
    file: str


@dataclass(frozen=True)
class UsbDevice:
    """A USB device as sysfs shows it."""

    port: str
    vendor: str
    product: str
    serial: str
    name: str


def udev_glob(pattern: str, value: str) -> bool:
    """Match like udev: shell glob, with ``|`` between alternatives."""
    return any(fnmatchcase(value, alt) for alt in pattern.split("|"))


def usb_matches(results: Iterable[LintResult]) -> tuple[UsbMatch, ...]:
    """The idVendor/idProduct pairs the parsed rules match on, in file order."""
    out: list[UsbMatch] = []
    for res in results:
        for r in res.rules:
            ids = {t.attr: t.value for t in r.tokens if t.key in ("ATTR", "ATTRS") and t.op == "=="}
            if "idVendor" in ids:
                m = UsbMatch(ids["idVendor"], ids.get("idProduct", "*"), Path(res.path).name)
                if m not in out:
                    out.append(m)
    return tuple(out)


def scan_usb(sysfs: Path = Path("/sys")) -> tuple[UsbDevice, ...]:
    """The USB devices present under ``sysfs/bus/usb/devices`` (none if it does not exist)."""
    base = Path(sysfs) / "bus/usb/devices"

    def read(d: Path, attr: str) -> str:
        try:
            return (d / attr).read_text(encoding="utf-8", errors="replace").strip()
        except OSError:
            return ""

    devices = []
    for d in sorted(base.glob("*")) if base.is_dir() else ():
        vendor = read(d, "idVendor")
        if vendor:
            devices.append(
                UsbDevice(
                    d.name, vendor, read(d, "idProduct"), read(d, "serial"), read(d, "product")
                )
            )
    return tuple(devices)
