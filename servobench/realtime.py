"""The best real-time footing the OS grants one thread, for the duration of a cyclic run.

:func:`realtime_thread` is a context manager the cyclic thread enters just
before its first cycle and leaves after its last. It asks, in order, and
keeps whatever is granted:

* **scheduling** -- ``SCHED_FIFO`` at :data:`FIFO_PRIORITY` for the calling
  thread (Linux applies ``sched_setscheduler(0, ...)`` to the calling thread
  only), else the lowest nice level the thread may take;
* **CPU affinity** -- the calling thread pinned to one CPU (the last one it
  may run on that no other cyclic thread holds, away from CPU 0 where
  interrupts and most daemons land);
* **memory locked** -- ``mlockall(MCL_CURRENT | MCL_FUTURE)`` through libc,
  so no page of the process is paged out or faulted in mid-cycle;
* **the garbage collector kept out** -- a full collection first, then the
  surviving objects frozen (``gc.freeze``) and automatic collection
  disabled;
* **the GIL handed over quickly** -- ``sys.setswitchinterval`` lowered to
  :data:`SWITCH_INTERVAL_S`, so a thread holding the GIL gives it up within
  that time once the cyclic thread wakes (a Python thread at ``SCHED_FIFO``
  still waits for the GIL);
* **helper threads** -- native thread ids the cyclic thread waits on (a CAN
  library's receive thread) get ``SCHED_FIFO`` one step below it;
* **every other thread of the process** (a log writer, a progress bar, a
  heartbeat) gets ``SCHED_FIFO`` :data:`GIL_HOLDER_PRIORITY` (the lowest):
  a thread that holds the GIL must not be preempted by other processes, or
  the cyclic thread waits for the GIL as long as the scheduler keeps that
  thread off the CPU (priority inversion through the GIL; measured under two
  busy processes: period jitter p99 1 ms, max 8 ms, without it). They sleep
  almost always, so they take little from the other processes.

What was obtained is the :class:`RealtimeGrant` the context yields; its
:meth:`RealtimeGrant.as_metadata` gives the log lines ``rt_policy``,
``rt_affinity``, ``rt_memory_locked``, ``rt_gc``, ``rt_switchinterval_s``
(with the reason wherever something was refused). Everything is reverted on
exit, in reverse order, whatever happened in between: scheduling, nice
level, affinity, locked memory, the collector and the switch interval.

Threads created by the cyclic thread while inside inherit its policy and
affinity: create helper threads (log writers) before entering.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import errno
import gc
import os
import sys
import threading
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

#: ``SCHED_FIFO`` priority of the cyclic thread (1..99; cyclictest's usual 80).
FIFO_PRIORITY = 80
#: Environment variable that turns it all off (``SERVOBENCH_REALTIME=off``), e.g. on a
#: machine where the bench must not take priority over other work; the log says so.
ENV_OFF = "SERVOBENCH_REALTIME"
#: ``SCHED_FIFO`` priority of the process's other threads during the run (the lowest).
GIL_HOLDER_PRIORITY = 1
#: GIL switch interval during the run [s] (CPython's default is 5 ms).
SWITCH_INTERVAL_S = 2e-5
#: ``mlockall`` flags (``<sys/mman.h>`` on Linux).
MCL_CURRENT, MCL_FUTURE = 1, 2


@dataclass(frozen=True)
class RealtimeGrant:
    """What the OS granted the cyclic thread (see the module docstring).

    Attributes
    ----------
    policy : str
        ``"SCHED_FIFO 80"``, or ``"SCHED_OTHER nice -20 (SCHED_FIFO refused: ...)"``.
    affinity : str
        The CPUs the thread runs on (``"1"``), or ``"all (reason)"``.
    memory_locked : str
        ``"yes"`` or ``"no (reason)"``.
    gc : str
        ``"frozen/disabled"``.
    switch_interval_s : float
        The GIL switch interval in force during the run [s].
    helpers : str
        What the helper threads got (``"2 threads SCHED_FIFO 79"``), ``""`` without any.
    other_threads : str
        What the process's other threads got (``"3 threads SCHED_FIFO 1"``), ``""`` without any.
    """

    policy: str
    affinity: str
    memory_locked: str
    gc: str
    switch_interval_s: float
    helpers: str = ""
    other_threads: str = ""

    @property
    def fifo(self) -> bool:
        return self.policy.startswith("SCHED_FIFO")

    def as_metadata(self) -> dict[str, str]:
        meta = {
            "rt_policy": self.policy,
            "rt_affinity": self.affinity,
            "rt_memory_locked": self.memory_locked,
            "rt_gc": self.gc,
            "rt_switchinterval_s": f"{self.switch_interval_s:g}",
        }
        if self.helpers:
            meta["rt_helpers"] = self.helpers
        if self.other_threads:
            meta["rt_other_threads"] = self.other_threads
        return meta


def _reason(err: OSError) -> str:
    return errno.errorcode.get(err.errno or 0, "") or str(err)


class _Undo:
    """A stack of undo actions, run in reverse order, each one's failure ignored."""

    def __init__(self) -> None:
        self.actions: list = []

    def push(self, action) -> None:
        self.actions.append(action)

    def run(self) -> None:
        while self.actions:
            action = self.actions.pop()
            with contextlib.suppress(Exception):
                action()


def _scheduling(undo: _Undo, priority: int) -> str:
    tid = threading.get_native_id()
    try:
        old_policy, old_param = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as err:
        refused = f"SCHED_FIFO refused: {_reason(err) if isinstance(err, OSError) else 'no sched_setscheduler'}"
    else:
        undo.push(lambda: os.sched_setscheduler(0, old_policy, old_param))
        return f"SCHED_FIFO {priority}"
    try:
        old_nice = os.getpriority(os.PRIO_PROCESS, tid)
    except OSError:
        return f"SCHED_OTHER ({refused})"
    for nice in range(-20, old_nice):
        try:
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except OSError:
            continue
        undo.push(lambda: os.setpriority(os.PRIO_PROCESS, tid, old_nice))
        return f"SCHED_OTHER nice {nice} ({refused})"
    return f"SCHED_OTHER nice {old_nice} ({refused}; no lower nice level permitted)"


def _affinity(undo: _Undo, cpu: int | None) -> str:
    try:
        old = os.sched_getaffinity(0)
    except (OSError, AttributeError):
        return "all (no sched_getaffinity)"
    if len(old) < 2 and cpu is None:
        return f"{','.join(map(str, sorted(old)))} (the only CPU allowed)"
    with _TAKEN_LOCK:  # concurrent cyclic threads (several drives) each get a CPU of their own
        free = set(old) - _TAKEN
        chosen = (max(free) if free else max(old)) if cpu is None else cpu
        try:
            os.sched_setaffinity(0, {chosen})
        except OSError as err:
            return f"all (sched_setaffinity refused: {_reason(err)})"
        _TAKEN.add(chosen)

    def restore() -> None:
        with _TAKEN_LOCK:
            _TAKEN.discard(chosen)
        os.sched_setaffinity(0, old)

    undo.push(restore)
    return str(chosen)


_TAKEN: set[int] = set()  # CPUs a cyclic thread is pinned to now
_TAKEN_LOCK = threading.Lock()


def _lock_memory(undo: _Undo) -> str:
    name = ctypes.util.find_library("c")
    if not name or not sys.platform.startswith("linux"):
        return "no (mlockall is Linux libc only)"
    libc = ctypes.CDLL(name, use_errno=True)
    if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
        code = ctypes.get_errno()
        return f"no ({errno.errorcode.get(code, code)}: raise the memlock limit or run as root)"
    undo.push(libc.munlockall)
    return "yes"


def _collector(undo: _Undo) -> str:
    was_enabled = gc.isenabled()
    gc.collect()
    gc.freeze()
    gc.disable()

    def restore() -> None:
        gc.unfreeze()
        if was_enabled:
            gc.enable()

    undo.push(restore)
    return "frozen/disabled"


def _switch_interval(undo: _Undo, interval_s: float) -> float:
    old = sys.getswitchinterval()
    sys.setswitchinterval(interval_s)
    undo.push(lambda: sys.setswitchinterval(old))
    return sys.getswitchinterval()


def process_threads() -> list[int]:
    """Native ids of this process's threads (Linux ``/proc/self/task``; empty elsewhere)."""
    try:
        return sorted(int(name) for name in os.listdir("/proc/self/task"))
    except (OSError, ValueError):
        return []


def _others(undo: _Undo, skip: set[int]) -> str:
    """Every other ``SCHED_OTHER`` thread of the process to ``SCHED_FIFO`` :data:`GIL_HOLDER_PRIORITY`."""
    tids = [t for t in process_threads() if t not in skip]
    raised = [t for t in tids if _raise_other(undo, t)]
    return f"{len(raised)} threads SCHED_FIFO {GIL_HOLDER_PRIORITY}" if raised else ""


def _raise_other(undo: _Undo, tid: int) -> bool:
    try:
        if os.sched_getscheduler(tid) != os.SCHED_OTHER:
            return False
        old_param = os.sched_getparam(tid)
        os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(GIL_HOLDER_PRIORITY))
    except OSError:  # gone, or not permitted
        return False
    undo.push(lambda: os.sched_setscheduler(tid, os.SCHED_OTHER, old_param))
    return True


def _helpers(undo: _Undo, native_ids: Sequence[int], priority: int) -> str:
    raised = 0
    refused = ""
    for tid in native_ids:
        try:
            old_policy, old_param = os.sched_getscheduler(tid), os.sched_getparam(tid)
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as err:
            refused = _reason(err)
            continue
        undo.push(lambda t=tid, p=old_policy, q=old_param: os.sched_setscheduler(t, p, q))
        raised += 1
    if not native_ids:
        return ""
    text = f"{raised} of {len(native_ids)} threads SCHED_FIFO {priority}"
    return text + (f" (refused: {refused})" if refused else "")


class _ProcessWide:
    """The process-wide settings (collector, switch interval, locked memory): taken by the
    first cyclic thread that enters, reverted by the last that leaves."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.holders = 0
        self.state: tuple[str, float, str] = ("", 0.0, "")
        self.undo = _Undo()

    def release(self) -> None:
        with self.lock:
            self.holders -= 1
            if self.holders == 0:
                self.undo.run()


_SHARED = _ProcessWide()


@contextlib.contextmanager
def realtime_thread(
    *,
    priority: int = FIFO_PRIORITY,
    cpu: int | None = None,
    lock_memory: bool = True,
    helper_threads: Sequence[int] = (),
    switch_interval_s: float = SWITCH_INTERVAL_S,
) -> Iterator[RealtimeGrant]:
    """Give the calling thread the best real-time footing the OS permits; revert on exit.

    Parameters
    ----------
    priority : int
        ``SCHED_FIFO`` priority asked for (1..99).
    cpu : int, optional
        CPU to pin to; default the highest-numbered CPU the thread may use.
    lock_memory : bool
        Ask for ``mlockall``.
    helper_threads : sequence of int
        Native ids of threads the cyclic thread waits on; they get ``priority - 1``.
    switch_interval_s : float
        GIL switch interval during the run [s].

    Yields
    ------
    RealtimeGrant
    """
    if os.environ.get(ENV_OFF, "").strip().lower() in ("0", "off", "no"):
        yield RealtimeGrant(f"SCHED_OTHER (turned off by {ENV_OFF})", "all (turned off)",
                            "no (turned off)", "enabled (turned off)", sys.getswitchinterval())  # fmt: skip
        return
    undo = _Undo()
    try:
        with _SHARED.lock:
            if _SHARED.holders == 0:
                process = _Undo()
                _SHARED.state = (
                    _collector(process),
                    _switch_interval(process, switch_interval_s),
                    _lock_memory(process) if lock_memory else "no (not asked)",
                )
                _SHARED.undo = process
            _SHARED.holders += 1
        undo.push(_SHARED.release)
        gc_state, interval, locked = _SHARED.state
        affinity = _affinity(undo, cpu)
        policy = _scheduling(undo, priority)
        fifo = policy.startswith("SCHED_FIFO")
        helpers = _helpers(undo, helper_threads, max(1, priority - 1)) if fifo else ""
        skip = {threading.get_native_id(), *helper_threads}
        others = _others(undo, skip) if fifo else ""
        yield RealtimeGrant(policy, affinity, locked, gc_state, interval, helpers, others)
    finally:
        undo.run()
