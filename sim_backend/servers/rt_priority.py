"""Real-time priority for a served drive: the best the operating system grants, and what that was.

A real drive has a processor of its own; a served simulated drive shares
the host's. ``serve-sim --rt-priority N`` narrows the difference:
:func:`request_priority` asks, for the calling process (on Linux, its calling
thread and every thread it starts afterwards, which inherit the policy), for
``SCHED_FIFO`` at priority ``N`` (1..99) and, when that is not permitted
(an unprivileged user without ``CAP_SYS_NICE`` or an RLIMIT_RTPRIO), for
the lowest nice value it may take, down to -20. It never raises on a
refusal: it returns :class:`Obtained`, whose :meth:`~Obtained.describe`
is the line ``serve-sim`` prints on stderr. Nothing here is left to
chance: each attempt's refusal is in the description.

The served drive's threads block on their sockets or ptys between
requests, so a SCHED_FIFO drive takes the processor only while it answers;
the kernel's real-time throttling (``sched_rt_runtime_us``) still bounds it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

#: Priority range of SCHED_FIFO on Linux.
FIFO_MIN, FIFO_MAX = 1, 99
#: Nice values: the best and the default.
NICE_BEST = -20


@dataclass(frozen=True)
class Obtained:
    """What :func:`request_priority` obtained.

    ``policy`` is ``"SCHED_FIFO"`` or ``"SCHED_OTHER"``; ``priority`` the
    FIFO priority (0 under SCHED_OTHER); ``nice`` the nice value in force;
    ``refused`` why the better options were not granted (empty when FIFO was).
    """

    policy: str
    priority: int
    nice: int
    refused: str = ""

    @property
    def realtime(self) -> bool:
        return self.policy == "SCHED_FIFO"

    def describe(self) -> str:
        if self.realtime:
            return f"real-time priority: SCHED_FIFO {self.priority}"
        return f"real-time priority: not granted ({self.refused}); SCHED_OTHER at nice {self.nice}"


def request_priority(priority: int) -> Obtained:
    """Ask for SCHED_FIFO at ``priority`` (1..99), else the best nice level; see the module doc."""
    if not FIFO_MIN <= priority <= FIFO_MAX:
        raise ValueError(f"real-time priority must be {FIFO_MIN}..{FIFO_MAX}, got {priority}")
    refused = []
    if hasattr(os, "sched_setscheduler"):
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            return Obtained("SCHED_FIFO", priority, os.getpriority(os.PRIO_PROCESS, 0))
        except OSError as err:
            refused.append(f"SCHED_FIFO: {err.strerror or err}")
    else:
        refused.append("SCHED_FIFO: not on this system")
    return Obtained("SCHED_OTHER", 0, _best_nice(refused), "; ".join(refused))


def _best_nice(refused: list[str]) -> int:
    """Lower the nice value as far as permitted; return the value in force."""
    current = os.getpriority(os.PRIO_PROCESS, 0)
    for nice in range(NICE_BEST, current):
        try:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
            return nice
        except OSError as err:
            if nice == NICE_BEST:
                refused.append(f"nice {NICE_BEST}: {err.strerror or err}")
    return current
