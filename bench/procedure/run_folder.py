"""The run folder of ``sidbe``: which files it holds, what each one is, and refusing to overwrite one.

Each excite-identify round streams to ``log-<i>.csv`` as its samples arrive
(``log-1.csv`` the first amplitude, ``log-2.csv`` the next, ...); the round
whose model is accepted is copied to ``log.csv``, the log ``model.json``
describes. ``model.json`` says the same in its ``files`` object. A
closed-loop run also keeps the logs it took before its rounds: ``probe.csv``
(the relay probe, when nothing was known of the axis) and ``hold-trial.csv``
(the trial a drive's own hold loop was fitted to). A folder that already
holds any of these is refused, never overwritten.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from servobench.bench.run.probe import PROBE_LOG
from servobench.errors import UsageError

#: Parent of the default run folders (the checkout's ``.gitignore`` lists it).
RUNS_DIR = "servobench-runs"
#: The trial under a drive's own hold loop (closed loop).
HOLD_TRIAL_LOG = "hold-trial.csv"
#: Files of a run folder: the accepted round's log and the model.
LOG_FILE, MODEL_FILE = "log.csv", "model.json"
#: Logs a closed-loop run writes before its rounds: the relay probe and the drive-hold trial.
CLOSED_LOOP_LOGS = {
    PROBE_LOG: "relay probe under the hold: what the axis was learnt from before round 1",
    HOLD_TRIAL_LOG: "trial under the drive's own hold: its loop gains were fitted to it",
}


def round_log_name(index: int) -> str:
    """The log of excite-identify round ``index`` (from 1)."""
    return f"log-{index}.csv"


def default_out_dir(base: Path | None = None) -> Path:
    """A new ``<base>/servobench-runs/<YYYYmmdd-HHMMSS>[-n]`` folder name (``base``: the
    current folder by default)."""
    root = (base or Path.cwd()) / RUNS_DIR
    stamp = time.strftime("%Y%m%d-%H%M%S")
    path = root / stamp
    n = 1
    while path.exists():
        n += 1
        path = root / f"{stamp}-{n}"
    return path


def check_run_folder(out_dir: str | Path) -> None:
    """Refuse a folder that holds an earlier run (its ``model.json``, ``log.csv``, ``log-N.csv``,
    or the closed loop's ``probe.csv`` and ``hold-trial.csv``).

    Raises
    ------
    UsageError
        Naming the files found and what to do.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise UsageError(f"{out} is a file, not a folder; choose another --out")
    if not out.is_dir():
        return
    found = sorted(p.name for p in out.iterdir() if p.name in (LOG_FILE, MODEL_FILE, *CLOSED_LOOP_LOGS)
                   or (p.name.startswith("log-") and p.suffix == ".csv"))  # fmt: skip
    if found:
        raise UsageError(
            f"{out} already holds a run ({', '.join(found)}); choose another --out, or move that "
            "run away first: nothing was overwritten"
        )


def describe_files(
    out_dir: Path, accepted_log: Path | None, iterations: Iterable[Any], *, closed: bool
) -> dict[str, str]:
    """``model.json``'s ``files`` object: file name -> what it holds.

    ``iterations`` are the rounds (:class:`~servobench.bench.procedure.sidbe.Iteration`);
    ``closed`` adds the closed loop's logs that ``out_dir`` holds.
    """
    source = accepted_log.name if accepted_log is not None else "the best round's log"
    out = {LOG_FILE: f"copy of {source}: the round this model was identified from "
                     "(the log to validate or diagnose it with)"}  # fmt: skip
    for it in iterations:
        fit = "no model" if it.fit_percent is None else f"fit {it.fit_percent:.2f} %"
        out[it.log_path.name] = f"round {it.index}, amplitude {it.amplitude:g}: {fit}; {it.action}"
    if closed:
        out.update({k: v for k, v in CLOSED_LOOP_LOGS.items() if (out_dir / k).exists()})
    return out
