"""Waiting for a deadline on ``time.monotonic()`` with sub-millisecond jitter.

Shared by the host's cycle schedule (:mod:`servobench.bench.run.runner`) and
the served drives' byte timing (:mod:`servobench.sim_backend.servers`).
"""

from __future__ import annotations

import time

#: The last stretch before a deadline that is spun rather than slept [s]:
#: ``time.sleep`` may overshoot by a scheduler tick, a spin does not.
SPIN_S = 5e-4


def sleep_until(deadline: float, spin_s: float = SPIN_S) -> None:
    """Return once ``time.monotonic() >= deadline``: sleep, then spin the last ``spin_s`` [s]."""
    remaining = deadline - time.monotonic()
    if remaining > spin_s:
        time.sleep(remaining - spin_s)
    while time.monotonic() < deadline:
        pass
