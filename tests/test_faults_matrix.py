"""Every fault kind on every transport it applies to, end to end across processes.

Each case serves the simulated drive with ``serve-sim --fault SPEC --state-file``,
streams the standard two runs with :func:`servobench.bench.run.runner.stream_runs` and holds
the outcome to :func:`servobench.bench.testing.fault_scenarios.judge`: the run rides through
(log equal to the fault-free reference run, row for row) or ends with the
expected typed error and a one-line message; the drive's own state report
shows it disabled or in fault with no torque; the log keeps every sample before
the fault cycle bit for bit and says ``status = incomplete`` with the reason.

The servers of one transport are started all at once (their start-up is most
of a case's time), then the cases run one after the other.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import pytest

from servobench.bench.log.io import read_log
from servobench.bench.testing.fault_scenarios import (
    CASES,
    Case,
    Outcome,
    ServerPool,
    judge,
    run_case,
    uncovered,
)
from servobench.sim_backend.faults.spec import TRANSPORTS

pytestmark = pytest.mark.slow  # every fault on every transport, 35 s

ORDERED = sorted(CASES, key=lambda c: TRANSPORTS.index(c.transport))


class Pools:
    """One :class:`ServerPool` per transport; the next transport's servers start in the
    background while the current transport's cases run (they mostly wait on the wire)."""

    def __init__(self, workdir: Path) -> None:
        self.workdir = workdir
        self.pools: dict[str, ServerPool] = {}
        self.references: dict[str, Outcome] = {}
        self._starting: dict[str, threading.Thread] = {}
        self._errors: dict[str, BaseException] = {}

    def _start(self, transport: str) -> None:
        if transport in self._starting or transport not in TRANSPORTS:
            return
        cases = [c for c in CASES if c.transport == transport]
        pool = ServerPool([None, *cases], transport, self.workdir)
        self.pools[transport] = pool

        def start() -> None:
            try:
                pool.start()
            except BaseException as err:  # raised in run()
                self._errors[transport] = err

        self._starting[transport] = thread = threading.Thread(target=start, daemon=True)
        thread.start()

    def run(self, case: Case) -> tuple[Outcome, Outcome]:
        tr = case.transport
        if tr not in self.references:
            for done in [t for t in self.pools if t != tr]:
                self.pools.pop(done).close()
            self._start(tr)
            self._starting[tr].join()
            if tr in self._errors:
                raise self._errors[tr]
            self.references[tr] = run_case(None, tr, self.workdir, self.pools[tr])
            assert self.references[tr].error is None, self.references[tr].message
            later = TRANSPORTS[TRANSPORTS.index(tr) + 1 :]
            if later:
                self._start(later[0])
        return run_case(case, tr, self.workdir, self.pools[tr]), self.references[tr]

    def close(self) -> None:
        for thread in self._starting.values():
            thread.join()
        for pool in self.pools.values():
            pool.close()
        self.pools = {}


@pytest.fixture(scope="module")
def pools(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Pools]:
    p = Pools(tmp_path_factory.mktemp("faults"))
    yield p
    p.close()


def test_every_kind_on_every_transport_has_a_case() -> None:
    assert uncovered() == []
    assert len({c.name for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", ORDERED, ids=lambda c: c.name)
def test_fault_outcome(case: Case, pools: Pools) -> None:
    outcome, reference = pools.run(case)
    assert judge(outcome, reference) == [], outcome.message
    state = outcome.state
    assert {"kind": case.kind, "cycle": case.cycle} in [
        {"kind": f["kind"], "cycle": f["cycle"]} for f in state["faults_injected"]
    ]
    log = read_log(outcome.log_path)
    if case.kind == "fault":
        assert state["fault_code"] == 0x2310
    elif case.kind == "busoff":
        assert state["fault_code"] == 0x8140  # abort connection: fault on bus-off
    elif case.kind == "dup" and case.transport == "serial":
        assert log.metadata["link_duplicates"] == "1"
    elif case.spec.startswith("exception") and case.rides:
        assert log.metadata["link_retries"] == "1"  # "busy" answered once, retried once
    if not case.rides:
        assert log.metadata["reason"] == outcome.message.replace("\n", " ")
        assert int(log.metadata["samples"]) == sum(len(r) for r in log.runs)


def test_bad_fault_spec_is_one_line_and_names_the_kinds() -> None:
    from servobench.errors import DriveConfigError
    from servobench.sim_backend.faults.spec import parse_plan

    with pytest.raises(DriveConfigError) as err:
        parse_plan("drop@5;crc@7", "modbus-tcp")
    message = str(err.value)
    assert "bad --fault 'drop@5'" in message and "exception" in message
    assert len(message.splitlines()) == 1
