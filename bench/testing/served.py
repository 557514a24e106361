"""Start ``servobench serve-sim`` in a child process and get its drive URL.

Used by the tests, the benchmarks and demos: the served simulated drive runs
in its own process, as a real drive is a separate machine, and the host side
talks to it over the real protocol stack.

Examples
--------
>>> with ServedSim("modbus-tcp", "sim://?M=0.1&B=1") as served:   # doctest: +SKIP
...     print(served.url)
"""

from __future__ import annotations

import contextlib
import os
import selectors
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence

from servobench.errors import DriveConnectionError, DriveTimeoutError

#: Longest wait for the server's first stdout line [s].
START_TIMEOUT_S = 30.0
#: Longest wait for a clean exit after SIGINT [s].
STOP_TIMEOUT_S = 10.0
#: How long a hung child has to write its stacks after SIGABRT before it is killed [s].
ABORT_WAIT_S = 5.0
#: Host URL keys that wait up to 2 s for a served drive's answer (and a drive-side watchdog of
#: 5 s, longer than that wait), per transport: for a host whose test judges what the drive
#: answers, not how fast. A served drive, or a host, starved of CPU on a busy machine is late,
#: not silent. The defaults (0.1 s for a TPDO or a serial reply, 0.25 s for a Modbus answer,
#: a 0.5 s watchdog) stay for the tests whose subject is the deadline itself.
#: Real-time priority of a served drive (``serve-sim --rt-priority``): below the host's
#: cyclic thread (80), above every time-shared process.
DRIVE_PRIORITY = 60
PATIENT_KEYS = {
    "canopen": "&pdo_timeout=2&watchdog=5",
    "modbus-tcp": "&timeout=2&watchdog=5",
    "modbus-rtu": "&timeout=2&watchdog=5",
    "serial": "&timeout=2&watchdog=5",
}


@contextlib.contextmanager
def at_drive_priority() -> Iterator[None]:
    """The calling thread, and every thread it starts meanwhile (Linux threads inherit the
    policy), at :data:`DRIVE_PRIORITY` where permitted, reverted at exit: for a test's stand-in
    of hardware (a wire, a talking device), which does not wait for a time-shared scheduler,
    so a timing the test measures is the stand-in's own, not the machine's load."""
    before = os.sched_getscheduler(0), os.sched_getparam(0)
    with contextlib.suppress(OSError):
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(DRIVE_PRIORITY))
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.sched_setscheduler(0, before[0], before[1])


class ServedSim:
    """A ``servobench serve-sim`` child process.

    Parameters
    ----------
    transport : str
        ``canopen``, ``modbus-tcp``, ``modbus-rtu`` or ``serial``.
    sim_url : str
        The plant as a ``sim://`` URL.
    extra_args : sequence of str
        More ``serve-sim`` options (``--node 3``, ``--fault ...``, ``--no-timestamp``,
        ``--rt-priority 50``).
    clock : str or None
        ``"real"`` (the axis moves in wall-clock time) or ``"lockstep"`` (one
        cycle per SYNC/read, exact): ``serve-sim --clock``; ``None``: serve-sim's
        default, ``real``.
    priority : int or None
        ``serve-sim --rt-priority`` unless ``extra_args`` gives one:
        :data:`DRIVE_PRIORITY` by default, as a real drive has a processor of its
        own (on a loaded machine a time-shared served drive answers a request
        100 ms late now and then, and a test of the protocol would read that as
        the drive's silence); ``None``: time-shared. Where SCHED_FIFO is not
        permitted serve-sim takes the best nice level and says so.
    """

    def __init__(
        self,
        transport: str,
        sim_url: str = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4",
        extra_args: Sequence[str] = (),
        clock: str | None = None,
        priority: int | None = DRIVE_PRIORITY,
    ) -> None:
        self.transport = transport
        self.sim_url = sim_url
        self.extra_args = list(extra_args) + (["--clock", clock] if clock else [])
        if priority is not None and "--rt-priority" not in self.extra_args:
            self.extra_args += ["--rt-priority", str(priority)]
        self.proc: subprocess.Popen[str] | None = None
        self.url = ""
        self.returncode: int | None = None
        self.stderr = ""

    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        cmd = [
            sys.executable, "-m", "servobench", "serve-sim",
            "--transport", self.transport, "--sim", self.sim_url, *self.extra_args,
        ]  # fmt: skip
        # faulthandler: a child that hangs on its way out is aborted, and its threads' stacks
        # go to its stderr, which the failure shows (see :meth:`stop`)
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONFAULTHANDLER": "1"}
        self.proc = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env
        )
        assert self.proc.stdout is not None
        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        deadline = time.monotonic() + timeout_s
        try:
            while time.monotonic() < deadline:
                if sel.select(timeout=0.1):
                    line = self.proc.stdout.readline()
                    if line.strip():
                        self.url = line.strip()
                        return self.url
                    if self.proc.poll() is not None:
                        break
                elif self.proc.poll() is not None:
                    break
        finally:
            sel.close()
        err = self._drain_stderr()
        self.stop()
        if self.returncode is not None:
            raise DriveConnectionError(
                f"serve-sim --transport {self.transport} exited ({self.returncode}): {err.strip()[-500:]}"
            )
        raise DriveTimeoutError(
            f"serve-sim --transport {self.transport} printed no URL in {timeout_s} s"
        )

    def _drain_stderr(self) -> str:
        if self.proc is None or self.proc.stderr is None or self.proc.poll() is None:
            return ""
        self.stderr += self.proc.stderr.read() or ""
        return self.stderr

    def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGINT, wait for a clean exit; if it hangs, SIGABRT (its threads' stacks to its
        stderr: ``PYTHONFAULTHANDLER``), then kill; return the exit status."""
        if self.proc is None:
            return self.returncode
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.send_signal(signal.SIGABRT)
                try:
                    self.proc.wait(ABORT_WAIT_S)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
        self.returncode = self.proc.returncode
        self._drain_stderr()
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        self.proc = None
        return self.returncode

    def __enter__(self) -> ServedSim:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
