"""Fault scenarios: one fault against a served drive, and a verdict on the outcome.

A :class:`Case` names a transport, a ``--fault`` spec and what the host must
do about it (ride through, or end the run with a given error). :func:`run_case`
starts ``servobench serve-sim`` with the fault and a state file, streams the
standard excitation (:func:`excitation`) with :func:`servobench.bench.run.runner.stream_runs`,
and returns an :class:`Outcome`; :func:`judge` lists what is wrong with it:

* the run rode through (log complete, equal to the fault-free reference row
  for row) or ended with the expected error and a one-line message;
* the drive ends with its torque off (disabled, or in fault), by its own
  state report;
* the log holds every sample before the fault cycle, equal to the
  fault-free reference run's, and is marked incomplete with the reason.

:data:`CASES` holds a case for every fault kind on every transport it applies
to (:func:`uncovered` proves it); the tests and ``benchmarks/faults.py`` run them.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from servobench.bench.logio import read_log
from servobench.bench.run.runner import stream_runs
from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.errors import DriveError
from servobench.sim_backend.faults.spec import KINDS, TRANSPORTS

#: The plant every scenario serves.
SIM_URL = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
#: Cycle rate of the scenarios [Hz].
FS_HZ = 1000.0
#: Samples of run 1 and run 2 of the standard excitation.
RUN_SAMPLES = (160, 80)
#: Cycle the faults hit (a sample of run 1; frozen feedback is caught 100 cycles later).
FAULT_CYCLE = 50
#: Rest between the runs [s].
SETTLE_S = 0.02
#: Longest wait for the drive's state report to show the torque off [s].
STATE_WAIT_S = 3.0
#: Extra ``serve-sim`` options per transport (faster emulated lines).
SERVE_ARGS: dict[str, tuple[str, ...]] = {
    "canopen": (),
    "modbus-tcp": (),
    "modbus-rtu": ("--baud", "1000000"),
    "serial": ("--baud", "1000000"),
}
#: Host URL keys of every scenario: stream as fast as the lock-step drive answers.
HOST_KEYS = "&pace=fast"
#: Host URL keys of the fault-free reference runs and of the cases that must not time out, on
#: transports whose client would otherwise take a drive late under CPU load for a silent one.
PATIENT = {"modbus-tcp": "&timeout=1", "modbus-rtu": "&timeout=1"}


@dataclass(frozen=True)
class Case:
    """One fault on one transport, and what must come of it.

    Attributes
    ----------
    transport : str
        ``serve-sim --transport``.
    spec : str
        The ``--fault`` item.
    rides : bool
        True: the run must complete with a log equal to the reference.
    error : str
        For a run that ends: the name of the error class raised.
    match : str
        For a run that ends: text the one-line message must contain.
    final_state : str
        Power state the drive must report when the host is done.
    host_keys : str
        Extra host URL keys (``&pdo_timeout=...``).
    """

    transport: str
    spec: str
    rides: bool = False
    error: str = ""
    match: str = ""
    final_state: str = "disabled"
    host_keys: str = ""

    @property
    def kind(self) -> str:
        return self.spec.partition("@")[0]

    @property
    def cycle(self) -> int:
        return int(self.spec.partition("@")[2].partition(":")[0])

    @property
    def name(self) -> str:
        return f"{self.transport}-{self.spec}"


def _cases() -> tuple[Case, ...]:
    n = FAULT_CYCLE
    out: list[Case] = []
    for tr in TRANSPORTS:
        out += [
            Case(tr, f"fault@{n}:0x2310", error="DriveFaultError", match="0x", final_state="fault"),
            Case(tr, f"freeze@{n}", error="DriveError", match="feedback frozen"),
        ]
    out += [
        Case("canopen", f"drop@{n}", error="DriveTimeoutError", match="no TPDO"),
        Case("canopen", f"delay@{n}:30", rides=True),
        Case("canopen", f"delay@{n}:300", error="DriveTimeoutError", match="no TPDO"),
        Case("canopen", f"dup@{n}", rides=True),
        Case(
            "canopen",
            f"busoff@{n}",
            error="DriveTimeoutError",
            match="no TPDO",
            final_state="fault",
        ),  # fmt: skip
        Case("canopen", f"emcy@{n}", error="DriveFaultError", match="EMCY 0xFF00"),
    ]
    for tr in ("modbus-tcp", "modbus-rtu"):
        out += [
            Case(tr, f"exception@{n}:6", rides=True),
            Case(tr, f"exception@{n}:4", error="DriveFaultError", match="exception 4"),
            Case(tr, f"exception@{n}:2", error="DriveConfigError", match="exception 2"),
            Case(tr, f"timeout@{n}", error="DriveTimeoutError", match="no answer"),
            Case(tr, f"delay@{n}:50", rides=True),
            Case(tr, f"delay@{n}:400", error="DriveTimeoutError", match="no answer"),
        ]
    out.append(Case("modbus-rtu", f"crc@{n}", error="DriveTimeoutError", match="no answer"))
    out += [
        Case("serial", f"garble@{n}", error="MalformedReplyError", match="garbled"),
        Case("serial", f"truncate@{n}", error="MalformedReplyError", match="garbled"),
        Case("serial", f"interleave@{n}", error="MalformedReplyError", match="garbled"),
        Case("serial", f"drop@{n}", error="DriveTimeoutError", match="no reply"),
        Case("serial", f"dup@{n}", rides=True),
        Case("serial", f"delay@{n}:30", rides=True),
        Case("serial", f"delay@{n}:250", error="DriveTimeoutError", match="no reply"),
    ]
    return tuple(replace(c, host_keys=_host_keys(c)) for c in out)


def _host_keys(case: Case) -> str:
    """The extra host URL keys a case needs."""
    if case.transport == "serial" and case.kind == "fault":
        return "&poll=0.005"  # the serial feedback reply carries no drive state: poll often
    # Modbus cases that must not time out wait up to 1 s for an answer (the default 0.25 s
    # stays for those that must): a served drive starved of CPU on a busy CI machine is late,
    # not wrong, and these cases judge the log and the drive's state, not the link's latency.
    if case.transport in PATIENT and case.error != "DriveTimeoutError":
        return PATIENT[case.transport]
    return case.host_keys


#: Every scenario: each fault kind on each transport it applies to, some twice.
CASES: tuple[Case, ...] = _cases()


def uncovered(cases: Sequence[Case] = CASES) -> list[str]:
    """``kind@transport`` pairs the grammar allows that no case exercises."""
    have = {(c.kind, c.transport) for c in cases}
    return sorted(
        f"{k}@{tr}" for k, kind in KINDS.items() for tr in kind.transports if (k, tr) not in have
    )


def excitation() -> list[tuple[int, np.ndarray]]:
    """The standard runs: a ±1 square wave (period 40 cycles), then 0.8 times it, shorter."""
    n1, n2 = RUN_SAMPLES
    u1 = np.where((np.arange(n1) // 20) % 2 == 0, 1.0, -1.0)
    return [(1, u1), (2, 0.8 * u1[:n2])]


@dataclass(frozen=True)
class Outcome:
    """What happened in one scenario."""

    case: Case
    error: BaseException | None
    log_path: Path
    state: dict[str, object]
    seconds: float
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def message(self) -> str:
        return "" if self.error is None else str(self.error)


def read_state(path: Path) -> dict[str, object]:
    """The served drive's last state report ({} if there is none yet)."""
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}


def wait_for_state(path: Path, states: Sequence[str], timeout_s: float = STATE_WAIT_S) -> dict:
    """Poll the state report until its state is one of ``states`` (or the time is up)."""
    deadline = time.monotonic() + timeout_s
    state = read_state(path)
    while state.get("state") not in states and time.monotonic() < deadline:
        time.sleep(0.01)
        state = read_state(path)
    return state


def _serve_args(case: Case | None, transport: str, workdir: Path) -> tuple[str, list[str]]:
    """``(name, serve-sim arguments)`` of a case (``None``: the fault-free reference)."""
    name = case.name if case is not None else f"{transport}-reference"
    args = [*SERVE_ARGS[transport], "--state-file", str(workdir / f"{name}.json")]
    if case is not None:
        args += ["--fault", case.spec]
    return name, args


class ServerPool:
    """``serve-sim`` processes for many scenarios, started all at once (their start-up
    is most of a scenario's time), handed out one by one.

    Parameters
    ----------
    cases : sequence of Case or None
        ``None`` stands for a fault-free reference of ``transport``.
    """

    def __init__(self, cases: Sequence[Case | None], transport: str, workdir: Path) -> None:

        workdir.mkdir(parents=True, exist_ok=True)
        self.workdir = workdir
        self._servers: dict[str, ServedSim] = {}
        for case in cases:
            tr = case.transport if case is not None else transport
            name, args = _serve_args(case, tr, workdir)
            self._servers[name] = ServedSim(tr, SIM_URL, args, clock="lockstep")

    def start(self) -> ServerPool:
        errors: list[BaseException] = []

        def start_one(server) -> None:
            try:
                server.start()
            except BaseException as err:  # reported below, after every start returned
                errors.append(err)

        threads = [threading.Thread(target=start_one, args=(s,)) for s in self._servers.values()]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        if errors:
            self.close()
            raise errors[0]
        return self

    def take(self, name: str):
        """The started server of scenario ``name`` (the caller stops it)."""
        return self._servers.pop(name)

    def close(self) -> None:
        for server in self._servers.values():
            if server.proc is not None and server.proc.poll() is None:
                server.proc.send_signal(signal.SIGINT)
        for server in self._servers.values():
            server.stop()
        self._servers = {}

    def __enter__(self) -> ServerPool:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


def run_case(
    case: Case | None, transport: str, workdir: Path, pool: ServerPool | None = None
) -> Outcome:
    """Serve the drive (with ``case``'s fault, or none), stream the standard runs, collect.

    Parameters
    ----------
    case : Case or None
        ``None`` runs the fault-free reference of ``transport``.
    transport : str
        The transport (``case.transport`` when a case is given).
    workdir : Path
        Where the log and the state report go.
    pool : ServerPool, optional
        Take the server from here (started beforehand) instead of starting one.
    """

    workdir.mkdir(parents=True, exist_ok=True)
    name, args = _serve_args(case, transport, workdir)
    log_path, state_path = workdir / f"{name}.csv", workdir / f"{name}.json"
    error: BaseException | None = None
    t0 = time.monotonic()
    served = pool.take(name) if pool is not None else ServedSim(transport, SIM_URL, args, clock="lockstep")
    try:
        if served.proc is None:
            served.start()
        url = served.url + HOST_KEYS + (case.host_keys if case is not None else PATIENT.get(transport, ""))
        try:
            with open_drive(url) as drive:
                stream_runs(drive, excitation(), FS_HZ, log_path, settle_s=SETTLE_S)
        except DriveError as err:
            error = err
        state = wait_for_state(state_path, ("disabled", "fault"))
    finally:
        served.stop()
    final = read_state(state_path)  # written at exit, before serve-sim's own clean-up
    return Outcome(
        case or Case(transport, "none@0", rides=True),
        error,
        log_path,
        final or state,
        time.monotonic() - t0,
    )


def _rows(log_path: Path) -> np.ndarray:
    """``run,t,u,v,x`` rows of a log, as written (t_host dropped)."""

    log = read_log(log_path)
    parts = [np.column_stack([np.full(len(r), r.run), r.t, r.u, r.v, r.x]) for r in log.runs]
    return np.concatenate(parts) if parts else np.zeros((0, 5))


def intact_rows(outcome: Outcome, reference: Outcome) -> int:
    """Leading rows of the outcome's log equal, bit for bit, to the reference's."""
    got, ref = _rows(outcome.log_path), _rows(reference.log_path)
    n = min(len(got), len(ref))
    differs = np.flatnonzero(np.any(got[:n] != ref[:n], axis=1))
    return int(differs[0]) if differs.size else n


def judge(outcome: Outcome, reference: Outcome) -> list[str]:
    """What is wrong with ``outcome`` (empty when the host behaved as the case demands)."""

    case, problems = outcome.case, []
    log = read_log(outcome.log_path)
    state = outcome.state
    rows = len(_rows(outcome.log_path))
    intact = intact_rows(outcome, reference)
    if case.rides:
        if outcome.error is not None:
            problems.append(f"should ride through, ended: {outcome.message}")
        if not log.complete or rows != len(_rows(reference.log_path)) or intact != rows:
            problems.append(f"log not equal to the reference ({intact} of {rows} rows equal)")
    else:
        err = outcome.error
        if err is None:
            problems.append("should end, completed")
        else:
            names = {cls.__name__ for cls in type(err).__mro__}
            if case.error not in names:
                problems.append(f"expected {case.error}, got {type(err).__name__}: {err}")
            if case.match not in str(err):
                problems.append(f"message lacks {case.match!r}: {err}")
            if len(str(err).splitlines()) != 1:
                problems.append(f"message is not one line: {str(err)!r}")
        if log.complete:
            problems.append("log not marked incomplete")
        if log.metadata.get("status") != "incomplete" or not log.metadata.get("reason"):
            problems.append("log lacks '# status = incomplete' and a reason")
        if intact < case.cycle - 1:
            problems.append(f"only {intact} rows intact before fault cycle {case.cycle}")
    if state.get("state") != case.final_state or not state.get("torque_off"):
        problems.append(
            f"drive ends {state.get('state')!r} (torque_off={state.get('torque_off')}), "
            f"expected {case.final_state!r}"
        )
    if state.get("command") != 0.0:
        problems.append(f"drive still applies command {state.get('command')}")
    if "enabled" not in [h.get("state") for h in state.get("history", [])]:
        problems.append("the drive was never enabled")
    return problems
