"""Which axis a log belongs to and when it was recorded: ``# axis`` and ``# time``.

Every log ``sidbe``, ``run`` and ``commission`` stream names its axis and
the time of the run in two metadata lines::

    # axis = canopen://can0?node=2
    # time = 2026-03-01T14:05:09+01:00

The runner writes them (:func:`run_identity`); ``servobench fleet`` reads
them back (:func:`log_identity`) to group the records of one axis and to
order them in time. The axis is the drive's address: the URL's scheme,
host, port and path and the query keys that select one axis on a shared
link (``channel``, ``node``, ``unit``, ``axis``), not the limits, timeouts
or plant keys, which may change between two runs of the same axis.
``commission`` names it by its configuration instead when ``[identity]``
gives an axis (``"Press 7 / Z"``, :func:`configured_axis`). The in-process
simulated drive ``sim://`` has no address: a simulated axis *is* its plant,
so its name is its plant file (``sim://?plant=press7.toml``), else its
physics, effect and device keys in a fixed order
(``sim://?B=1&M=0.1&fc_neg=0.4&fc_pos=0.5&seed=3``), without the safety and
pace keys and the drive's control tick (``tick``: how the drive samples, not
what the plant is); two ``sim://`` logs of different plants are two axes. The time is ISO
8601 with the local UTC offset, to the second.

A log without these lines (written by another tool, or before they existed)
is named by its file name and dated by its modification time.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from datetime import datetime
from pathlib import Path

from servobench.errors import LogFormatError, one_line

#: Metadata key of the axis name.
AXIS_KEY = "axis"
#: Metadata key of the run's start time (ISO 8601).
TIME_KEY = "time"
#: Query keys that select one axis on a link shared by several.
ADDRESS_KEYS = ("channel", "node", "unit", "axis")
#: Keys that do not tell one simulated plant from another: those every drive URL takes
#: (limits, watchdog, pace: servobench.drivers.base.COMMON_QUERY_KEYS) and the simulated
#: drive's own control tick (``tick``, a property of the drive, not of the plant).
NOT_PLANT_KEYS = frozenset({"max_u", "max_v", "xmin", "xmax", "watchdog", "pace", "tick", "drift"})
#: The scheme of the in-process simulated drive, named by its plant.
SIM_SCHEME = "sim"


def axis_of_url(url: object) -> str:
    """The axis name of a drive URL: its address without limits, timeouts or plant keys.

    ``canopen://can0?node=2&max_u=3`` -> ``canopen://can0?node=2``;
    ``sim://?M=0.1&pace=real`` -> ``sim://?M=0.1`` (a simulated axis is its plant). ``url`` is a
    :class:`~servobench.drivers.url.DriveURL` (or anything with ``scheme``,
    ``host``, ``port``, ``path`` and ``query``).
    """
    where = getattr(url, "host", "") or ""
    port = getattr(url, "port", None)
    if port is not None:
        where += f":{port}"
    query: Mapping[str, str] = getattr(url, "query", {}) or {}
    if url.scheme == SIM_SCHEME:  # type: ignore[attr-defined]
        plant = {"plant": query["plant"]} if "plant" in query else {
            k: v for k, v in query.items() if k not in NOT_PLANT_KEYS}  # fmt: skip
        address = "&".join(f"{k}={plant[k]}" for k in sorted(plant))
        return f"sim://?{address}" if address else "sim://"
    address = "&".join(f"{k}={query[k]}" for k in ADDRESS_KEYS if k in query)
    name = f"{url.scheme}://{where}{getattr(url, 'path', '') or ''}"  # type: ignore[attr-defined]
    return f"{name}?{address}" if address else name


def configured_axis(machine: str, axis: str) -> str:
    """The axis name a configuration gives (``[identity]`` of ``bench.toml``), "" for none.

    ``("Press 7", "Z")`` -> ``"Press 7 / Z"``; ``("", "Z")`` -> ``"Z"``; no axis -> "".
    The machine goes first because axis letters repeat from machine to machine.
    """
    machine, axis = one_line(machine).strip(), one_line(axis).strip()
    if not axis:
        return ""
    return f"{machine} / {axis}" if machine else axis


def now_iso() -> str:
    """The current local time as ISO 8601 with its UTC offset, to the second."""
    return datetime.now().astimezone().isoformat(timespec="seconds")


def run_identity(drive: object) -> dict[str, str]:
    """``{"axis": ..., "time": ...}`` for the header of a log streamed from ``drive`` now."""
    return {AXIS_KEY: axis_of_url(drive.url), TIME_KEY: now_iso()}  # type: ignore[attr-defined]


def parse_time(text: str) -> datetime:
    """An ISO 8601 time as an aware :class:`~datetime.datetime` (no offset: local time).

    Raises
    ------
    LogFormatError
        ``text`` is not ISO 8601.
    """
    try:
        stamp = datetime.fromisoformat(text.strip())
    except ValueError:
        raise LogFormatError(
            f"metadata time = {one_line(text)[:60]!r} is not ISO 8601 "
            "(write e.g. '# time = 2026-03-01T14:05:09+01:00')"
        ) from None
    return stamp if stamp.tzinfo is not None else stamp.astimezone()


def log_identity(metadata: Mapping[str, str], path: str | os.PathLike[str]) -> tuple[str, str]:
    """``(axis, time)`` of a log: from its metadata, else its file name and modification time.

    The time is returned as normalised ISO 8601 with a UTC offset.

    Raises
    ------
    LogFormatError
        The ``time`` metadata is not ISO 8601.
    OSError
        The file's modification time cannot be read.
    """
    path = Path(path)
    axis = one_line(str(metadata.get(AXIS_KEY, ""))).strip() or path.stem
    text = str(metadata.get(TIME_KEY, "")).strip()
    stamp = parse_time(text) if text else datetime.fromtimestamp(path.stat().st_mtime).astimezone()
    return axis, stamp.isoformat()
