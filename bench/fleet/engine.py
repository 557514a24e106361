"""Run the per-log jobs on Dask distributed: a local cluster or an existing scheduler.

One code path for both: :func:`connect` yields a ``distributed.Client``,
either on a ``LocalCluster`` of ``workers`` single-threaded worker
processes started here (one worker: a thread of this process, on Dask's
``inproc`` transport), or on the scheduler at ``scheduler``
(``tcp://host:8786``) with the workers already connected to it. Then
:func:`run_on` splits the logs into batches (a few per worker, so the
per-task overhead of the scheduler is paid per batch, not per log, and the
load still balances), ships the paths, and gathers the rows in input
order, whatever the order the batches finish in.

Failures stay in rows: a batch whose worker died (``KilledWorker``) or
that could not run gets an error row per log. Ctrl-C (or any error in the
loop) cancels what is pending and closes the client and the cluster it
started; :class:`FleetInterrupted` carries the rows done by then.

Dask is imported here only, when a fleet runs: the rest of servobench does
not need the ``fleet`` extra.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from servobench.bench.fleet.job import process_batch
from servobench.bench.fleet.sources import LogSource
from servobench.bench.fleet.table import FleetRow
from servobench.errors import ServobenchError, UsageError, one_line

#: Batches per worker: enough to balance uneven logs, few enough to keep overhead small.
BATCHES_PER_WORKER = 4
#: Most logs in one batch (keeps the progress bar moving on big fleets).
MAX_BATCH = 16
#: How long to wait for a scheduler to answer, and for a worker to join it [s].
CONNECT_TIMEOUT_S = 15.0
#: Modules the workers' forkserver imports once for all of them.
FORKSERVER_PRELOAD = ("distributed", "numpy", "servobench.bench.dsp.iir", "servobench.bench.fleet.job",
                      "servobench.bench.identify.auto")  # fmt: skip
#: Error text of the logs that a Ctrl-C left undone.
INTERRUPTED = "not processed: interrupted (Ctrl-C)"

ProgressCallback = Callable[[int, int], None]
T = TypeVar("T")


class FleetEngineError(ServobenchError):
    """Dask is missing, or the cluster cannot be started or reached."""


class FleetInterrupted(KeyboardInterrupt):
    """Ctrl-C during a fleet run; ``rows`` holds every log's row (undone ones say so)."""

    def __init__(self, rows: list[FleetRow]) -> None:
        super().__init__("interrupted (Ctrl-C)")
        self.rows = rows


def require_fleet_extra() -> None:
    """Raise :class:`FleetEngineError` unless Dask distributed and pyarrow are installed."""
    import importlib.util

    missing = [m for m in ("distributed", "pyarrow") if importlib.util.find_spec(m) is None]
    if missing:
        raise FleetEngineError(
            f"servobench fleet needs {' and '.join(missing)}: pip install 'servobench[fleet]'"
        )


def _distributed() -> Any:
    require_fleet_extra()
    import distributed

    return distributed


@contextlib.contextmanager
def connect(workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` on a new local cluster, or on the scheduler at ``scheduler``.

    Parameters
    ----------
    workers : int, optional
        Worker processes of the local cluster (default: the machine's cores); 1 runs the one
        worker in this process.
    scheduler : str, optional
        Address of a running scheduler (``tcp://host:8786``); ``workers`` must then be None.
    """
    distributed = _distributed()
    if scheduler and workers is not None:
        raise UsageError("give --workers or --scheduler, not both")
    if workers is not None and workers < 1:
        raise UsageError(f"--workers must be >= 1, got {workers}")
    with contextlib.ExitStack() as stack:
        if scheduler:
            client = _remote(distributed, scheduler)
            stack.callback(client.close)
        else:
            n = workers or os.cpu_count() or 1
            # one worker runs in this process: no worker process to keep from Ctrl-C
            ignore = contextlib.nullcontext() if n == 1 else _workers_ignore_ctrl_c(distributed)
            with ignore, _ctrl_c_after_start():
                cluster = _local_cluster(distributed, n)
                stack.callback(cluster.close)
                client = distributed.Client(cluster, set_as_default=False)
                stack.callback(client.close)
        yield client


@contextlib.contextmanager
def _workers_ignore_ctrl_c(distributed: Any) -> Iterator[None]:
    """Start the local workers with SIGINT ignored, so that Ctrl-C is this process's alone.

    A terminal's Ctrl-C reaches every process of the foreground group: each
    worker would die mid-task (or mid-start) with a traceback of its own.
    Workers are forked from a forkserver that starts while SIGINT is ignored
    here for a moment; it and its children keep ignoring it, while this
    process handles Ctrl-C and closing the cluster stops them. The
    forkserver also preloads the identification code, which makes workers
    start faster. Where there is no forkserver (Windows), nothing changes.
    """
    import multiprocessing
    import multiprocessing.forkserver
    import os
    import signal
    import threading

    import dask

    if (
        "forkserver" not in multiprocessing.get_all_start_methods()
        or threading.current_thread() is not threading.main_thread()
    ):
        yield
        return
    with dask.config.set({"distributed.worker.multiprocessing-method": "forkserver"}):
        context = distributed.utils.get_mp_context()
        context.set_forkserver_preload(list(FORKSERVER_PRELOAD))
        # The forkserver loads numpy once for all workers: it must see the worker
        # environment Dask would give each of them (one BLAS thread per worker).
        environ = {
            k: str(v) for k, v in dask.config.get("distributed.nanny.pre-spawn-environ", {}).items()
        }
        saved = {k: os.environ.get(k) for k in environ}
        previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
        try:
            os.environ.update(environ)
            multiprocessing.forkserver.ensure_running()
        finally:
            signal.signal(signal.SIGINT, previous)
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        yield


@contextlib.contextmanager
def _ctrl_c_after_start() -> Iterator[None]:
    """Hold a Ctrl-C back while the cluster starts, then raise it (a half-started cluster
    cannot be closed cleanly; a started one can)."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    pressed: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if pressed:
        raise KeyboardInterrupt


def _local_cluster(distributed: Any, n: int) -> Any:
    try:
        return distributed.LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            # One worker runs in this process (a thread of its own): a process would only cost
            # its start and imports, several seconds beside a fleet of a few logs.
            processes=n > 1,
            host="127.0.0.1" if n > 1 else None,  # in one process: Dask's inproc transport
            dashboard_address=":0",
            # A worker's failures reach the client as the task's exception, which fleet reports
            # per log; what the workers would print besides is shutdown noise (a heartbeat to a
            # scheduler already closing, with its traceback, on a busy machine).
            silence_logs=logging.CRITICAL,
        )
    except Exception as err:  # noqa: BLE001 -- distributed raises many kinds here
        raise FleetEngineError(
            f"could not start a local Dask cluster of {n} workers: {one_line(str(err))}"
        ) from None


def _probe(scheduler: str) -> None:
    """Fail at once, not after the client's time-out, when nothing listens at a ``tcp://`` address."""
    import socket
    from urllib.parse import urlsplit

    parts = urlsplit(scheduler if "://" in scheduler else f"tcp://{scheduler}")
    if parts.scheme != "tcp" or not parts.hostname or parts.port is None:
        return  # other protocols: the client's own time-out applies
    try:
        socket.create_connection((parts.hostname, parts.port), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as err:
        raise FleetEngineError(
            f"cannot reach the Dask scheduler at {one_line(scheduler)} ({err.strerror or err}): "
            "start it with 'dask scheduler', or drop --scheduler for a local cluster"
        ) from None


def _remote(distributed: Any, scheduler: str) -> Any:
    logging.getLogger("distributed").setLevel(logging.ERROR)
    _probe(scheduler)
    try:
        client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise FleetEngineError(
            f"cannot reach the Dask scheduler at {one_line(scheduler)} ({one_line(str(err)) or type(err).__name__}): "
            "start it with 'dask scheduler', or drop --scheduler for a local cluster"
        ) from None
    try:
        client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError):
        client.close()
        raise FleetEngineError(
            f"no Dask worker joined the scheduler at {one_line(scheduler)} within "
            f"{CONNECT_TIMEOUT_S:g} s: start one with 'dask worker {one_line(scheduler)}'"
        ) from None
    return client


def worker_count(client: Any) -> int:
    """Workers connected to the client's scheduler (at least 1)."""
    return max(1, len(client.scheduler_info().get("workers", {})))


def batches(sources: Sequence[T], workers: int) -> list[list[T]]:
    """Consecutive batches: about :data:`BATCHES_PER_WORKER` per worker, at most :data:`MAX_BATCH` logs."""
    if not sources:
        return []
    size = math.ceil(len(sources) / (max(1, workers) * BATCHES_PER_WORKER))
    size = max(1, min(MAX_BATCH, size))
    return [list(sources[i : i + size]) for i in range(0, len(sources), size)]


def run_on(
    client: Any,
    sources: Sequence[LogSource],
    diagnose: bool = False,
    progress: ProgressCallback | None = None,
) -> list[FleetRow]:
    """Process every source on ``client``'s workers; rows in the order of ``sources``.

    ``progress(done, total)`` is called as batches finish.
    """
    distributed = _distributed()
    parts = batches(sources, worker_count(client))
    futures = client.map(process_batch, parts, diagnose=diagnose, pure=False)
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[list[FleetRow] | None] = [None] * len(parts)
    done = 0
    try:
        for future in distributed.as_completed(futures, loop=client.loop):
            i = index[future.key]
            results[i] = _batch_rows(future, parts[i])
            done += len(parts[i])
            if progress is not None:
                progress(done, len(sources))
    except KeyboardInterrupt:
        client.cancel(futures)
        raise FleetInterrupted(_assemble(results, parts, INTERRUPTED)) from None
    except BaseException:
        client.cancel(futures)
        raise
    return _assemble(results, parts, "not processed")


def _batch_rows(future: Any, part: list[LogSource]) -> list[FleetRow]:
    try:
        return list(future.result())
    except Exception as err:  # noqa: BLE001 -- a dead worker or a task that could not run
        reason = one_line(f"{type(err).__name__}: {err}")[:300]
        return [FleetRow(s.name, error=f"worker failed: {reason}") for s in part]


def _assemble(
    results: list[list[FleetRow] | None], parts: list[list[LogSource]], missing: str
) -> list[FleetRow]:
    rows: list[FleetRow] = []
    for got, part in zip(results, parts, strict=True):
        rows.extend(got if got is not None else [FleetRow(s.name, error=missing) for s in part])
    return rows


def map_on(
    client: Any, function: Callable[..., Any], items: Sequence[Any], **kwargs: Any
) -> list[Any]:
    """``function(item, **kwargs)`` of every item on ``client``'s workers, in batches, in order.

    For work after the rows, such as drawing each axis's figure; an error is raised here.
    """
    parts = batches(items, worker_count(client))
    futures = client.map(_apply_all, parts, function=function, pure=False, **kwargs)
    try:
        results = client.gather(futures)
    except BaseException:
        client.cancel(futures)
        raise
    return [out for part in results for out in part]


def _apply_all(items: Sequence[Any], function: Callable[..., Any], **kwargs: Any) -> list[Any]:
    return [function(item, **kwargs) for item in items]


def run_fleet(
    sources: Sequence[LogSource],
    *,
    diagnose: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: ProgressCallback | None = None,
) -> list[FleetRow]:
    """:func:`run_on` on :func:`connect` ``(workers, scheduler)``; the cluster is closed after."""
    with connect(workers, scheduler) as client:
        return run_on(client, sources, diagnose, progress)


def run_sequential(sources: Sequence[LogSource], diagnose: bool = False) -> list[FleetRow]:
    """The same rows in one process, one log after the other (the reference of a Dask run)."""
    return process_batch(list(sources), diagnose)
