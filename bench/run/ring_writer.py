"""Log rows handed from the cyclic thread to a writer thread through a preallocated ring.

The cyclic thread calls :meth:`RingLogWriter.append`, which stores the row
in a ``(capacity, columns)`` array allocated before the run and advances a
counter: no formatting, no file I/O, no lock. A writer thread wakes every
:data:`FLUSH_S`, formats the rows that arrived since (one
:meth:`~servobench.bench.log.io.LogWriter.append_block`, which flushes to the
OS) and frees their slots. So the log is still written as samples arrive: a
host killed outright loses at most the rows of the last ``FLUSH_S`` (plus
the one being formatted).

The ring never drops a row: when the writer falls ``capacity`` rows behind,
:meth:`append` waits for it (and counts the waits, :attr:`stalls`).
:meth:`close` drains every row before it returns, so the trailer
(:meth:`LogWriter.finish`) always follows the last sample, also on Ctrl-C
and errors. A failure of the writer thread (a full disk) is raised in the
cyclic thread by the next :meth:`append` or by :meth:`close`.

The writer thread runs on every CPU at ``SCHED_FIFO`` 1 (the lowest real-time
priority, else ``SCHED_OTHER``) whatever the thread that created it had been
granted: below the cyclic thread, but never preempted by other processes
while it holds the GIL (:mod:`servobench.realtime`).
"""

from __future__ import annotations

import contextlib
import os
import threading
import time

import numpy as np

from servobench.bench.log.io import LogWriter
from servobench.realtime import GIL_HOLDER_PRIORITY

#: Rows the ring holds: several seconds at 1 kHz.
RING_ROWS = 8192
#: Writer thread period [s]: the most a killed host loses.
FLUSH_S = 0.005


class RingLogWriter:
    """Rows of a :class:`LogWriter` written by a thread of their own (see the module docstring).

    Parameters
    ----------
    writer : LogWriter
        The open log (header written); rows go to it in order.
    capacity : int
        Rows the ring holds.
    flush_s : float
        Writer thread period [s].
    """

    def __init__(self, writer: LogWriter, capacity: int = RING_ROWS, flush_s: float = FLUSH_S) -> None:
        self.writer = writer
        self.capacity = int(capacity)
        self.flush_s = float(flush_s)
        self._ring = np.zeros((self.capacity, len(writer.columns)))
        self._written = 0  # rows stored by the cyclic thread
        self._taken = 0  # rows written to the file by the writer thread
        self.stalls = 0  #: appends that waited for a full ring
        self._failure: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="servobench-log-writer", daemon=True)
        self._thread.start()

    @property
    def rows(self) -> int:
        """Rows appended so far (written or still in the ring)."""
        return self._written

    @property
    def path(self):
        return self.writer.path

    def append(self, *values: float) -> None:
        """Store one row (values in column order); called by the cyclic thread only."""
        if self._failure is not None:
            self._raise()
        n = self._written
        if n - self._taken >= self.capacity:
            self.stalls += 1
            while n - self._taken >= self.capacity:
                if self._failure is not None:
                    self._raise()
                time.sleep(self.flush_s / 5)
        self._ring[n % self.capacity] = values
        self._written = n + 1

    def _raise(self) -> None:
        raise OSError(f"writing the log {self.writer.path} failed: {self._failure}") from self._failure

    def _run(self) -> None:
        with contextlib.suppress(OSError, AttributeError):  # not the cyclic thread's CPU or priority
            os.sched_setaffinity(0, range(os.cpu_count() or 1))
            try:  # the lowest real-time priority: it holds the GIL only briefly, never preempted
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(GIL_HOLDER_PRIORITY))
            except OSError:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        try:
            while not self._stop.wait(self.flush_s):
                self._drain()
            self._drain()
        except BaseException as err:  # surfaced in the cyclic thread
            self._failure = err

    def _drain(self) -> None:
        end = self._written
        start = self._taken
        while start < end:
            a = start % self.capacity
            b = min(end - start, self.capacity - a) + a
            block = self._ring[a:b]
            self.writer.append_block(*block.T)
            start += b - a
            self._taken = start

    def close(self) -> None:
        """Write every row still in the ring and stop the writer thread."""
        self._stop.set()
        self._thread.join()
        if self._failure is not None:
            self._raise()
        self._drain()  # rows appended after the thread's last look
