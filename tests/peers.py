"""The programs the tests pair with, and how the test command gets them onto a fresh machine.

The README's test command (``python -m pytest -q``) does the whole job: before
any test runs, :func:`check` (called from ``tests/conftest.py`` on the xdist
controller only, never in a worker) looks for every peer in :data:`PEERS`
that the selected test files need. As root it installs what is missing
(Debian packages: one ``apt-get update``, then one ``apt-get install -y``;
pip packages into the running environment), quietly. Without root, a missing
peer stops the session at once with one line naming the peer and the command
that installs it, and a non-zero exit: a peer is never skipped silently.

A new peer is one row of :data:`PEERS`: its name, how to probe for it, how
to install it, and the test files that need it.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
#: Exit status of a session stopped for a missing peer (pytest's own "usage error").
EXIT_MISSING = pytest.ExitCode.USAGE_ERROR


def on_path(program: str) -> Callable[[], bool]:
    """Probe: ``program`` is an executable on ``PATH``."""
    return lambda: shutil.which(program) is not None


def importable(module: str) -> Callable[[], bool]:
    """Probe: ``module`` imports in the running interpreter."""
    return lambda: importlib.util.find_spec(module) is not None


@dataclass(frozen=True)
class Installer:
    """How one kind of peer is installed.

    Attributes
    ----------
    name : str
        ``debian`` or ``pip``.
    needs_root : bool
        Installing needs root (system packages).
    """

    name: str
    needs_root: bool

    def commands(self, packages: Sequence[str]) -> list[list[str]]:
        """The commands that install ``packages``, in order."""
        if self.name == "debian":
            return [["apt-get", "update", "-qq"], ["apt-get", "install", "-y", "-qq", *packages]]
        return [[sys.executable, "-m", "pip", "install", "-q", "--disable-pip-version-check", *packages]]

    def hint(self, package: str) -> str:
        """The command a user runs to install ``package`` by hand."""
        if self.name == "debian":
            return f"sudo apt-get install -y {package}"
        return f"python -m pip install {package}"


DEBIAN = Installer("debian", needs_root=True)
PIP = Installer("pip", needs_root=False)


@dataclass(frozen=True)
class Peer:
    """One program the tests pair with.

    Attributes
    ----------
    name : str
        What it is called in messages.
    present : callable
        Probe: True when it is installed.
    installer : Installer
        :data:`DEBIAN` or :data:`PIP`.
    package : str
        What the installer installs.
    needed_by : tuple of str
        Test files (relative to ``tests/``) that need it.
    """

    name: str
    present: Callable[[], bool]
    installer: Installer
    package: str
    needed_by: tuple[str, ...]


#: The test files that make a private EtherCAT link (a veth pair in a namespace of their own).
ETHERCAT_TESTS = ("test_ethercat_soem.py", "test_ethercat_drive.py")

#: Every peer the suite pairs with. Add a row for a new one.
PEERS: tuple[Peer, ...] = (
    # renders the commissioning record headless; every figure must decode
    Peer("chromium", on_path("chromium"), DEBIAN, "chromium", ("test_commission_report.py",)),
    # libmodbus's command-line client against the served Modbus drive
    Peer("mbpoll", on_path("mbpoll"), DEBIAN, "mbpoll", ("test_modbus_mbpoll.py",)),
    # SOEM, the open EtherCAT master, against the served slave; and ``ip`` for its veth link
    Peer("pysoem", importable("pysoem"), PIP, "pysoem>=1.1.13", ETHERCAT_TESTS),
    Peer("iproute2", on_path("ip"), DEBIAN, "iproute2", ETHERCAT_TESTS),
)


class PeerMissing(Exception):
    """A peer is missing and cannot be installed here; ``str()`` is the one line to print."""


def needed(peers: Iterable[Peer], selected: Sequence[Path]) -> list[Peer]:
    """The peers some selected path needs (a path selects the test files at or below it)."""
    out = []
    for peer in peers:
        files = [TESTS / f for f in peer.needed_by]
        if any(f == s or s in f.parents for f in files for s in selected):
            out.append(peer)
    return out


def ensure(
    peers: Sequence[Peer],
    *,
    is_root: bool,
    run: Callable[[list[str]], subprocess.CompletedProcess] | None = None,
    say: Callable[[str], None] = lambda line: None,
) -> list[Peer]:
    """Install the missing ``peers`` where that is allowed; return those installed.

    Raises
    ------
    PeerMissing
        A peer is missing and may not be installed (needs root), or its
        installation failed, or it is still missing afterwards.
    """
    run = run or _run
    missing = [p for p in peers if not p.present()]
    for peer in missing:
        if peer.installer.needs_root and not is_root:
            raise PeerMissing(
                f"servobench tests: {peer.name} is not installed and installing it needs root; "
                f"install it with: {peer.installer.hint(peer.package)}"
            )
    for installer in dict.fromkeys(p.installer for p in missing):
        group = [p for p in missing if p.installer == installer]
        say(f"servobench tests: installing {', '.join(p.name for p in group)} ({installer.name})")
        for command in installer.commands([p.package for p in group]):
            done = run(command)
            if done.returncode != 0:
                tail = (done.stderr or "").strip().splitlines()[-1:] or ["no message"]
                raise PeerMissing(
                    f"servobench tests: {' '.join(command)} failed ({tail[0]}); "
                    f"install {', '.join(p.name for p in group)} by hand: "
                    + "; ".join(p.installer.hint(p.package) for p in group)
                )
    for peer in missing:
        if not peer.present():
            raise PeerMissing(
                f"servobench tests: {peer.name} is still missing after installing it; "
                f"install it with: {peer.installer.hint(peer.package)}"
            )
    return missing


def _run(command: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    return subprocess.run(command, capture_output=True, text=True, env=env, check=False)


def selected_paths(config: pytest.Config) -> list[Path]:
    """The files and folders the command line selects (node ids cut at ``::``)."""
    base = config.invocation_params.dir
    return [(base / arg.split("::")[0]).resolve() for arg in config.args]


def check(config: pytest.Config, peers: Sequence[Peer] = PEERS, *, is_root: bool | None = None) -> None:
    """The session hook: make the selected tests' peers present, or stop the session.

    Runs once, on the xdist controller (a worker has ``config.workerinput``).
    """
    if hasattr(config, "workerinput") or config.option.collectonly:
        return
    if is_root is None:
        is_root = os.geteuid() == 0
    try:
        ensure(needed(peers, selected_paths(config)), is_root=is_root, say=_say)
    except PeerMissing as err:
        pytest.exit(str(err), returncode=EXIT_MISSING)


def _say(line: str) -> None:
    print(line, file=sys.stderr, flush=True)
