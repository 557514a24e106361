"""Two served drives on one CAN bus, two hosts streaming at once: no cross-talk.

Drive A (node 2) starts the socketcand hub; drive B (node 3, another plant)
joins it as a TCP client (``serve-sim --can socketcand://HOST:PORT``). Each
host runs :func:`servobench.bench.run.runner.stream_runs` in its own thread with its own
excitation. Every CANopen host sends SYNC and the lock-step drives clock on
every SYNC they listen to, so each pair gets its own SYNC COB-ID
(``sync_cob``, written to the drive's 0x1005) and each host its own
heartbeat node (``host_node``, so neither drive's watchdog is fed by the
other host). Each log must then equal the lock-step simulation of its own
plant and command; with the default shared SYNC the same set-up does not.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from servobench.bench.logio import read_log
from servobench.bench.run.runner import stream_runs
from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import open_drive
from servobench.drivers.url import parse_drive_url
from servobench.errors import DriveConfigError, DriveError
from servobench.sim_backend.physics.plant import PlantParams, simulate

SIM_A = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
SIM_B = "sim://?M=0.2&B=0.5&fc_pos=0.3&fc_neg=0.3"
PARAMS = {"A": PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4),
          "B": PlantParams(M=0.2, B=0.5, coulomb_pos=0.3, coulomb_neg=0.3)}  # fmt: skip
FS_HZ = 1000.0
N = 600


def excitations() -> dict[str, list[tuple[int, np.ndarray]]]:
    k = np.arange(N)
    u_a = np.where((k // 50) % 2 == 0, 1.2, -1.2)
    u_b = 0.9 * np.sign(np.sin(2 * np.pi * k / 170.0) + 0.3)
    return {"A": [(1, u_a), (2, 0.7 * u_a)], "B": [(1, u_b), (2, 0.6 * u_b)]}


@pytest.fixture(scope="module")
def bus() -> Iterator[dict[str, str]]:
    """Drive A on its own hub, drive B joined to it; yields their URLs."""
    with ServedSim("canopen", SIM_A, ["--node", "2"], clock="lockstep") as a:
        q = parse_drive_url(a.url)
        hub = f"socketcand://{q.get_str('host')}:{q.get_str('port')}"
        with ServedSim("canopen", SIM_B, ["--node", "3", "--can", hub], clock="lockstep") as b:
            yield {"A": a.url, "B": b.url}


def stream_both(urls: dict[str, str], keys: dict[str, str], tmp: Path) -> dict[str, object]:
    """Both hosts at once, each in its own thread; returns log paths or the error raised."""
    results: dict[str, object] = {}
    runs = excitations()
    barrier = threading.Barrier(2)

    def host(name: str) -> None:
        path = tmp / f"{name}.csv"
        try:
            with open_drive(urls[name] + "&pace=fast" + keys[name]) as drive:
                barrier.wait(timeout=10)
                stream_runs(drive, runs[name], FS_HZ, path, settle_s=0.05)
            results[name] = path
        except (DriveError, threading.BrokenBarrierError) as err:
            results[name] = err

    threads = [threading.Thread(target=host, args=(n,)) for n in ("A", "B")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return results


def matches_plant(path: Path, name: str) -> bool:
    log = read_log(path)
    for number, u in excitations()[name]:
        run = log.run(number)
        if len(run) != len(u) or not np.array_equal(run.u, u):
            return False
        if number == 1:  # run 1 starts from rest: the plain lock-step simulation
            v, x = simulate(u, FS_HZ, PARAMS[name])
            if not (np.allclose(run.v, v, atol=1e-6) and np.allclose(run.x, x, atol=1e-6)):
                return False
    return log.complete


def test_own_sync_per_drive_no_cross_talk(bus: dict[str, str], tmp_path: Path) -> None:
    # pdo_timeout 0.5 s: two served drives and two hosts on a busy CI machine answer late, not
    # wrongly; this test judges whose SYNC clocks whom, not the latency
    patient = "&pdo_timeout=0.5"
    keys = {"A": "&sync_cob=0x80&host_node=126" + patient, "B": "&sync_cob=0x90&host_node=125" + patient}
    results = stream_both(bus, keys, tmp_path)
    for name in ("A", "B"):
        assert isinstance(results[name], Path), results[name]
        assert matches_plant(results[name], name), f"drive {name}'s log is not its own plant's"
    # drive B's drive clock advanced once per its own SYNC only (no extra cycles from A)
    log_b = read_log(results["B"])
    np.testing.assert_allclose(np.diff(log_b.run(1).t), 1e-3, atol=1e-9)


def test_shared_sync_is_cross_talk(bus: dict[str, str], tmp_path: Path) -> None:
    """The control: both on 0x80, each drive is clocked by both hosts' SYNCs."""
    keys = {"A": "&host_node=124", "B": "&host_node=123"}
    results = stream_both(bus, keys, tmp_path)
    broken = [
        n
        for n in ("A", "B")
        if not isinstance(results[n], Path) or not matches_plant(results[n], n)
    ]
    assert broken, "two hosts on one SYNC COB-ID should disturb each other"


@pytest.mark.parametrize(
    ("cob", "ok"),
    [("0x80", True), ("0x90", True), ("0x100", True), ("0x0", False), ("0x702", False),
     ("0x800", False), ("0x82", False), ("0x182", False), ("0x5FF", False)],
)  # fmt: skip
def test_sync_cob_must_be_unrestricted_and_not_the_nodes_own(cob: str, ok: bool) -> None:
    url = f"canopen://vcan0?interface=virtual&node=2&sync_cob={cob}"
    if ok:
        assert open_drive(url).sync_cob == int(cob, 16)  # constructed, not connected
        return
    with pytest.raises(DriveConfigError, match="sync_cob"):
        open_drive(url)
