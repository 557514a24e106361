"""Naming the signals of a file written by another tool: ``t=Time,u=Input*35.15,x=Position``.

One mapping syntax for CSV headers (``--columns``) and MATLAB variables
(``--mat-map``): ``signal=expression`` items separated by commas, where an
expression is a product of names (a column or variable) and numbers
(``u=vir*gtau``, ``x=Position*0.001``). Signals are ``run``, ``t``, ``u``,
``v``, ``x`` or any extra column name.

:func:`apply_map` evaluates a mapping over named arrays; :func:`read_mat`
gives the variables of a ``.mat`` file as named arrays and, without a
mapping, answers with the variables it holds.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from servobench.errors import LogFormatError, one_line

#: The signals a log's columns may name (run 1 = u1 experiment, run 2 = u2).
SIGNALS = ("run", "t", "u", "v", "x")
#: The columns of a closed-loop log beyond :data:`SIGNALS`: the excitation and the held position.
CLOSED_LOOP_SIGNALS = ("u_exc", "x_ref")
#: Signals every log needs.
REQUIRED = ("t", "u")

Named = Mapping[str, "np.ndarray | float"]


def parse_map(spec: str | Mapping[str, str] | None) -> dict[str, str]:
    """``"t=t,u=vir*gtau"`` -> ``{"t": "t", "u": "vir*gtau"}`` (empty for None)."""
    if spec is None:
        return {}
    if isinstance(spec, Mapping):
        return dict(spec)
    out: dict[str, str] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        key, sep, expr = item.partition("=")
        if not sep or not key.strip() or not expr.strip():
            raise LogFormatError(f"bad variable mapping {item!r}; expected name=variable[*factor]")
        out[key.strip()] = expr.strip()
    return out


def format_map(mapping: Mapping[str, str]) -> str:
    return ",".join(f"{k}={v}" for k, v in mapping.items())


def sources(mapping: Mapping[str, str]) -> set[str]:
    """The names (not numbers) a mapping's expressions use."""
    out = set()
    for expr in mapping.values():
        for factor in expr.split("*"):
            factor = factor.strip()
            if not _is_number(factor):
                out.add(factor)
    return out


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def apply_map(named: Named, mapping: Mapping[str, str], where: str, kind: str) -> dict[str, np.ndarray]:
    """Evaluate every ``signal=expression`` of ``mapping`` over ``named`` arrays.

    ``kind`` is ``"column"`` or ``"variable"``, for the error messages.

    Raises
    ------
    LogFormatError
        A name ``named`` lacks, or a value that is not numeric.
    """
    out: dict[str, np.ndarray] = {}
    for signal, expr in mapping.items():
        value: np.ndarray | float = 1.0
        for factor in (f.strip() for f in expr.split("*")):
            if _is_number(factor):
                value = value * float(factor)
                continue
            if factor not in named:
                raise LogFormatError(
                    f"{where}: no {kind} {factor!r} for {signal} (has {describe(named)})"
                )
            try:
                value = value * np.asarray(named[factor], dtype=float)
            except (TypeError, ValueError):
                raise LogFormatError(f"{where}: {kind} {factor!r} is not numeric") from None
        out[signal] = np.atleast_1d(np.asarray(value, dtype=float)).ravel()
    return out


def describe(named: Named, limit: int = 12) -> str:
    """``"qm [24841], gtau (scalar), ..."``: what a file holds, for an error message."""
    parts = []
    for name in sorted(named):
        try:
            size = np.size(named[name])
        except Exception:  # an object array numpy cannot size
            size = -1
        shown = one_line(name)[:40]
        parts.append(f"{shown} (scalar)" if size == 1 else f"{shown} [{size}]")
    if len(parts) > limit:
        parts = [*parts[:limit], f"... {len(parts) - limit} more"]
    return ", ".join(parts) or "nothing"


def read_mat(path: Path, spec: str | Mapping[str, str] | None) -> tuple[dict[str, np.ndarray], str]:
    """The signals of a MATLAB file by ``spec``, and the mapping used (as text).

    Without ``spec``, variables named like the signals (``t``, ``u``, ``v``,
    ``x``, ``run``) are used; when those lack ``t`` or ``u`` the error lists
    the variables the file holds and how to map them.
    """
    from scipy.io import loadmat

    where = one_line(str(path))
    mapping = parse_map(spec)
    try:
        mat = loadmat(str(path), squeeze_me=True)
    except Exception as err:  # scipy raises several types for a bad file
        raise LogFormatError(
            f"{where}: not a readable MATLAB file ({one_line(str(err))[:200]})"
        ) from None
    variables = {k: v for k, v in mat.items() if not k.startswith("__")}
    if not mapping:
        mapping = {k: k for k in SIGNALS + CLOSED_LOOP_SIGNALS if k in variables}
        missing = [c for c in REQUIRED if c not in mapping]
        if missing:
            raise LogFormatError(
                f"{where}: no --mat-map given and the mapping lacks {', '.join(missing)}: "
                f"the file holds {describe(variables)}; "
                "pass e.g. --mat-map t=t,u=vir*gtau,x=qm with these names"
            )
    columns = apply_map(variables, mapping, where, "variable")
    missing = [c for c in REQUIRED if c not in columns]
    if missing:
        raise LogFormatError(
            f"{where}: mapping lacks {', '.join(missing)}; pass e.g. --mat-map t=t,u=vir*gtau,x=qm"
        )
    return columns, format_map(mapping)
