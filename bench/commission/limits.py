"""Confirm the safety limits and hand them to the Drive layer.

The limits (max command, max velocity, allowed travel) come from the
configuration and from the drive URL; where both give one the tighter wins.
They are confirmed at the terminal, or taken as they are under ``--yes`` (then
every one must be given). The confirmed limits go into the drive URL query
(``max_u``, ``max_v``, ``xmin``, ``xmax``), so the Drive layer enforces them on
every transport: commands are clamped, and leaving the velocity or travel
envelope stops and disables the axis.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TextIO
from urllib.parse import urlencode, urlsplit

from servobench.bench.commission.config import LIMIT_KEYS, LimitSettings
from servobench.bench.commission.errors import CommissionRefused
from servobench.drivers.url import DriveURL, parse_drive_url

_DESCRIPTIONS = {
    "max_u": "max |command| (torque/current) [command units]",
    "max_v": "max |velocity| [velocity units/s]",
    "xmin": "travel lower bound [position units] (-inf: unlimited)",
    "xmax": "travel upper bound [position units] (inf: unlimited)",
}


@dataclass(frozen=True)
class ConfirmedLimits:
    """Limits the technician confirmed.

    Attributes
    ----------
    max_u : float
        Largest ``|command|`` [command units], finite and > 0.
    max_v : float
        Largest ``|velocity|`` [velocity units/s], finite and > 0.
    xmin, xmax : float
        Allowed travel [position units]; infinite for unlimited travel.
    how : str
        ``"terminal"`` or ``"config (--yes)"``.
    """

    max_u: float
    max_v: float
    xmin: float
    xmax: float
    how: str = ""

    def __post_init__(self) -> None:
        for key in ("max_u", "max_v"):
            value = getattr(self, key)
            if not (math.isfinite(value) and value > 0):
                raise CommissionRefused(f"limit {key} must be a finite number > 0, got {value}")
        if math.isnan(self.xmin) or math.isnan(self.xmax) or not self.xmin < self.xmax:
            raise CommissionRefused(f"allowed travel must have xmin < xmax, got [{self.xmin}, {self.xmax}]")

    def as_dict(self) -> dict[str, float]:
        return {k: getattr(self, k) for k in LIMIT_KEYS}

    def describe(self, units: Mapping[str, str] | None = None) -> str:
        """``|u| <= 5 N m, |v| <= 20 rad/s, x in [-inf, inf] rad`` (units when given)."""
        unit = {k: f" {v}" for k, v in (units or {}).items() if v}
        return (
            f"|u| <= {self.max_u:g}{unit.get('u', '')}, |v| <= {self.max_v:g}{unit.get('v', '')}, "
            f"x in [{self.xmin:g}, {self.xmax:g}]{unit.get('x', '')}"
        )


def merge_limits(config: LimitSettings, url: DriveURL) -> LimitSettings:
    """Limits from the configuration and the URL query; the tighter where both give one."""
    values: dict[str, float | None] = {}
    for key in LIMIT_KEYS:
        a = getattr(config, key)
        b = url.get_float(key) if key in url.query else None
        if a is None or b is None:
            values[key] = a if b is None else b
        else:
            values[key] = max(a, b) if key == "xmin" else min(a, b)
    return LimitSettings(**values)


def url_with_limits(url: str, limits: ConfirmedLimits) -> str:
    """``url`` with its ``max_u``, ``max_v``, ``xmin``, ``xmax`` query keys set to ``limits``.

    Unlimited travel is expressed by leaving ``xmin``/``xmax`` out. Other query
    keys are kept in order.
    """
    parsed = parse_drive_url(url)
    parts = urlsplit(url.strip())
    query = {k: v for k, v in parsed.query.items() if k not in LIMIT_KEYS}
    for key, value in limits.as_dict().items():
        if math.isfinite(value):
            query[key] = repr(float(value))
    text = f"{parts.scheme}://{parts.netloc}{parts.path}"
    return f"{text}?{urlencode(query, safe='/:')}" if query else text


def limits_from_config(settings: LimitSettings) -> ConfirmedLimits:
    """The limits for ``--yes``: every one must be given, else :class:`CommissionRefused`."""
    missing = settings.missing()
    if missing:
        raise CommissionRefused(
            f"--yes needs every limit, missing: {', '.join(missing)}; "
            "add them to the [limits] table of --config (see examples/bench.toml; "
            "use xmin = -inf and xmax = inf for unlimited travel)"
        )
    return ConfirmedLimits(**{k: float(getattr(settings, k)) for k in LIMIT_KEYS}, how="config (--yes)")


AskFloat = Callable[[str, "float | None"], float]
AskYesNo = Callable[[str], bool]


class _Lines:
    """A text stream read line by line as a terminal would give it: no newline, EOF raises."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream

    def readline(self) -> str:
        line = self.stream.readline()
        if not line:
            raise EOFError
        return line.rstrip("\r\n")


class TerminalPrompter:
    """Ask the limits with :mod:`rich.prompt` (``stream`` replaces stdin in tests).

    End of input is a refusal: nothing is confirmed by a closed terminal.
    """

    def __init__(self, console=None, stream: TextIO | None = None) -> None:
        self.console = console
        self.stream = _Lines(stream) if stream is not None else None

    def _ask(self, prompt_cls, text: str, **kwargs):
        try:
            return prompt_cls.ask(text, console=self.console, stream=self.stream, **kwargs)
        except EOFError:
            raise CommissionRefused("no answer at the terminal (end of input); nothing was moved") from None

    def ask_float(self, text: str, default: float | None) -> float:
        from rich.prompt import FloatPrompt

        if default is None:
            return float(self._ask(FloatPrompt, text))
        return float(self._ask(FloatPrompt, text, default=default))

    def ask_yes_no(self, text: str) -> bool:
        from rich.prompt import Confirm

        return bool(self._ask(Confirm, text, default=False))


def confirm_at_terminal(settings: LimitSettings, prompter: TerminalPrompter) -> ConfirmedLimits:
    """Ask every limit (the configured value is the default) and a final yes/no."""
    values = {
        key: prompter.ask_float(_DESCRIPTIONS[key], getattr(settings, key)) for key in LIMIT_KEYS
    }
    limits = ConfirmedLimits(**values, how="terminal")
    if not prompter.ask_yes_no(f"Commission with {limits.describe()}?"):
        raise CommissionRefused("limits not confirmed; nothing was moved")
    return limits
