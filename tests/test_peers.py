"""The test command gets its peers itself: installed as root, else one line and a non-zero exit.

Nothing is uninstalled here: the probes of the peers under test are fakes,
and so is the command runner where an installation would run.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import peers
import pytest

TESTS = Path(__file__).resolve().parent


class FakeProbe:
    """A peer that appears once :meth:`install` ran."""

    def __init__(self, present: bool = False) -> None:
        self.present = present

    def __call__(self) -> bool:
        return self.present


def fake_peer(name: str, probe: FakeProbe, installer: peers.Installer = peers.DEBIAN) -> peers.Peer:
    return peers.Peer(name, probe, installer, name, ("test_x.py",))


class Runner:
    """Records the commands; the install command makes the given probes present."""

    def __init__(self, installs: dict[str, FakeProbe], fail: str = "") -> None:
        self.installs, self.fail, self.commands = installs, fail, []

    def __call__(self, command: list[str]) -> subprocess.CompletedProcess:
        self.commands.append(command)
        if self.fail and self.fail in command:
            return subprocess.CompletedProcess(command, 100, "", "E: Unable to locate package\n")
        for package, probe in self.installs.items():
            if "install" in command and package in command:
                probe.present = True
        return subprocess.CompletedProcess(command, 0, "", "")


def test_a_missing_peer_without_root_stops_the_session_with_one_line(tmp_path):
    """The whole mechanism as the README's command meets it: conftest hook, pytest.exit."""
    (tmp_path / "conftest.py").write_text(
        f"import sys\nsys.path.insert(0, {str(TESTS)!r})\nimport peers\n"
        "ROW = peers.Peer('nosuch-peer', peers.on_path('nosuch-peer-xyz'), peers.DEBIAN,\n"
        "                 'nosuch-peer', ('test_x.py',))\n"
        "peers.TESTS = __import__('pathlib').Path(__file__).parent\n"
        "def pytest_configure(config):\n"
        "    peers.check(config, (ROW,), is_root=False)\n"
    )
    (tmp_path / "test_x.py").write_text("def test_ran():\n    open('ran', 'w').close()\n")
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_x.py"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == int(peers.EXIT_MISSING) != 0
    lines = [line for line in (done.stdout + done.stderr).splitlines() if line.strip()]
    assert len(lines) == 1, lines
    assert "nosuch-peer is not installed" in lines[0]
    assert "sudo apt-get install -y nosuch-peer" in lines[0]
    assert not (tmp_path / "ran").exists()  # no test ran


def test_without_root_the_first_missing_peer_is_named_and_nothing_runs():
    a, b = FakeProbe(present=True), FakeProbe()
    runner = Runner({})
    with pytest.raises(peers.PeerMissing) as err:
        peers.ensure([fake_peer("here", a), fake_peer("gone", b)], is_root=False, run=runner)
    assert str(err.value).count("\n") == 0
    assert "gone is not installed" in str(err.value) and "apt-get install -y gone" in str(err.value)
    assert runner.commands == []


def test_as_root_the_missing_peers_are_installed_with_one_update_and_one_install():
    a, b, c = FakeProbe(), FakeProbe(present=True), FakeProbe()
    runner = Runner({"a": a, "c": c})
    said = []
    done = peers.ensure(
        [fake_peer("a", a), fake_peer("b", b), fake_peer("c", c)], is_root=True, run=runner, say=said.append
    )
    assert [p.name for p in done] == ["a", "c"]
    assert runner.commands == [
        ["apt-get", "update", "-qq"],
        ["apt-get", "install", "-y", "-qq", "a", "c"],
    ]
    assert said == ["servobench tests: installing a, c (debian)"]


def test_nothing_missing_runs_nothing():
    runner = Runner({})
    assert peers.ensure([fake_peer("a", FakeProbe(present=True))], is_root=True, run=runner) == []
    assert runner.commands == []


def test_a_pip_peer_installs_without_root_into_the_running_interpreter():
    a = FakeProbe()
    runner = Runner({"a": a})
    peers.ensure([fake_peer("a", a, peers.PIP)], is_root=False, run=runner)
    (command,) = runner.commands
    assert command[:4] == [sys.executable, "-m", "pip", "install"] and command[-1] == "a"


def test_a_failed_installation_is_one_line_naming_the_command():
    a = FakeProbe()
    with pytest.raises(peers.PeerMissing) as err:
        peers.ensure([fake_peer("a", a)], is_root=True, run=Runner({"a": a}, fail="install"))
    text = str(err.value)
    assert "\n" not in text
    assert "apt-get install -y -qq a failed (E: Unable to locate package)" in text
    assert "sudo apt-get install -y a" in text


def test_an_installation_that_leaves_the_peer_missing_says_so():
    with pytest.raises(peers.PeerMissing, match="a is still missing after installing it"):
        peers.ensure([fake_peer("a", FakeProbe())], is_root=True, run=Runner({}))


def test_only_the_selected_files_peers_are_needed():
    by_name = {p.name: p for p in peers.PEERS}
    assert {p.name for p in peers.needed(peers.PEERS, [TESTS])} == set(by_name)
    assert peers.needed(peers.PEERS, [TESTS / "test_layout.py"]) == []
    assert peers.needed(peers.PEERS, [TESTS / "test_modbus_mbpoll.py"]) == [by_name["mbpoll"]]
    assert peers.needed(peers.PEERS, [TESTS.parent]) == list(peers.PEERS)


def test_every_row_names_test_files_that_exist():
    for peer in peers.PEERS:
        for name in peer.needed_by:
            assert (TESTS / name).is_file(), (peer.name, name)
