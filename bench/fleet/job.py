"""The work done for one log, wherever it runs: read, identify, diagnose, one row.

A worker receives paths, never data: :func:`process_batch` opens each log
itself (the same file system is assumed on every worker, as for any
batch system), so the scheduler moves a few hundred bytes per log. Nothing
here raises for a bad log: its row carries the one-line reason in
``error`` and the batch goes on.

:func:`process_batch` is the same function a sequential run calls, so a
distributed run gives the same rows as a plain loop.
"""

from __future__ import annotations

from collections.abc import Sequence

from servobench.bench.fleet.sources import LogSource
from servobench.bench.fleet.table import DIAGNOSED, EFFECT_SEPARATOR, FleetRow
from servobench.errors import ServobenchError, one_line

#: Longest error text kept in a row [characters].
MAX_ERROR_CHARS = 300


def process_batch(sources: Sequence[LogSource], diagnose: bool = False) -> list[FleetRow]:
    """:func:`process_log` on each source, in order."""
    return [process_log(source, diagnose) for source in sources]


def process_log(source: LogSource, diagnose: bool = False) -> FleetRow:
    """Identify (and with ``diagnose``, diagnose) one log; never raises for a bad log.

    Parameters
    ----------
    source : LogSource
        ``name`` goes into the ``log`` column, ``path`` is opened.
    diagnose : bool
        Also run the discrepancy workflow (effects, velocity gaps).

    Returns
    -------
    FleetRow
        Its ``error`` names what went wrong, "" when nothing did.
    """
    from servobench.bench.identify.auto import identify
    from servobench.bench.log.identity import log_identity
    from servobench.bench.log.io import read_log

    row = _named_by_file(source)
    try:
        log = read_log(source.path)
        axis, time = log_identity(log.metadata, source.path)
        row = FleetRow(source.name, axis, time)
        result = identify(log)
    except Exception as err:  # noqa: BLE001 -- any failure belongs in the row, not the batch
        return _replace(row, error=_reason(err).replace(source.path, source.name))
    model = result.model
    row = FleetRow(
        source.name, axis, time, model.M, model.B, model.pole, model.dc_gain,
        model.coulomb_pos, model.coulomb_neg, result.fit_percent, result.method,
        units=result.units.parameters(),
    )  # fmt: skip
    if diagnose:
        row = _with_diagnosis(row, log)
    if not log.complete and not row.error:
        reason = log.metadata.get("reason", "no 'status = complete' trailer")
        row = _replace(row, error=f"incomplete log ({one_line(reason)}): the run was cut short")
    return row


def _with_diagnosis(row: FleetRow, log: object) -> FleetRow:
    from servobench.bench.diagnose.workflow import diagnose

    try:
        d = diagnose(log)  # type: ignore[arg-type]
    except Exception as err:  # noqa: BLE001
        return _replace(row, error=f"diagnose: {_reason(err)}")
    names = EFFECT_SEPARATOR.join(e.name for e in d.effects)
    base = d.base  # refitted together with the effects
    return _replace(
        row, effects=names, gap_before=float(d.gap_before), gap_after=float(d.gap_after),
        model=" + ".join(["base", *(e.name for e in d.effects)]),
        **{f"diagnosed_{k}": float(base[k]) for k in DIAGNOSED},
    )  # fmt: skip


def _replace(row: FleetRow, **changes: object) -> FleetRow:
    from dataclasses import replace

    return replace(row, **changes)


def _named_by_file(source: LogSource) -> FleetRow:
    """A row named by the file alone (for a log that cannot be read)."""
    from servobench.bench.log.identity import log_identity

    try:
        axis, time = log_identity({}, source.path)
    except OSError:
        axis, time = "", ""
    return FleetRow(source.name, axis, time)


def _reason(err: BaseException) -> str:
    """One line: the message of a servobench error, else the type and message."""
    text = str(err) if isinstance(err, ServobenchError) else f"{type(err).__name__}: {err}"
    if isinstance(err, OSError) and err.strerror:
        text = f"{err.filename or ''}: {err.strerror}".lstrip(": ")
    text = one_line(text).strip() or type(err).__name__
    return text[:MAX_ERROR_CHARS]
