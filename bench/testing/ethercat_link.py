"""A private EtherCAT link for tests: a veth pair inside a network namespace of its own.

:func:`run_on_link` runs ``function(master_iface, url)`` from a Python file in a
child process that lives in a new network namespace: as root ``unshare -n``
(where the served slave may take real-time priority), otherwise a new user
and network namespace (``unshare -Urn``: no root needed where unprivileged
user namespaces are allowed), each the other's fallback. Inside it the
child creates the veth pair :data:`MASTER_IFACE` <-> :data:`SLAVE_IFACE`,
starts ``servobench serve-sim --transport ethercat --iface SLAVE_IFACE`` on one
end (:class:`~servobench.bench.testing.served.ServedSim`) and calls the
function with the other end and the URL the server printed; the function's
return value (JSON) comes back to the caller. No interface outside the
namespace is ever touched, and everything in it vanishes with the child.

:func:`link_unavailable` says why no such link can be made here (no
``unshare`` or ``ip``, user namespaces forbidden, no raw sockets), or
``None`` when it can; tests fail with that reason (never skip: the link is what they test).

Run as a module, it is the child: ``python -m servobench.bench.testing.ethercat_link
FILE FUNCTION SIMURL [SERVE-ARG...]`` (inside the namespace).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from typing import Any

MASTER_IFACE = "ecmaster"
SLAVE_IFACE = "ecslave"
#: Marks the result line on the child's stdout.
RESULT_MARK = "ETHERCAT-LINK-RESULT "
#: Longest run of one child [s] (start, the function, stop).
RUN_TIMEOUT_S = 180.0

_PROBE = (
    "import socket; s = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x88A4)); "
    "s.bind(('lo', 0)); s.close()"
)


#: The ways to a namespace of one's own, tried in order (:func:`namespaces`).
USER_NETNS, NETNS = ["unshare", "-Urn"], ["unshare", "-n"]


def namespaces() -> tuple[list[str], ...]:
    """As root a network namespace first, then a user + network namespace; otherwise the
    user + network namespace alone (no root needed where unprivileged user namespaces are
    allowed). Root goes without the user namespace where it can: inside one the kernel
    grants no SCHED_FIFO, and the served slave, like a real drive with its own processor,
    runs at real-time priority (:data:`~servobench.bench.testing.served.DRIVE_PRIORITY`)."""
    root = hasattr(os, "geteuid") and os.geteuid() == 0
    return (NETNS, USER_NETNS) if root else (USER_NETNS, NETNS)
_chosen: list[str] | None = None


def _probe(prefix: list[str]) -> str | None:
    script = f"ip link add {MASTER_IFACE} type veth peer name {SLAVE_IFACE} && "
    script += f'{sys.executable} -c "{_PROBE}"'
    try:
        done = subprocess.run([*prefix, "sh", "-c", script], capture_output=True, text=True,
                              timeout=30)  # fmt: skip
    except (OSError, subprocess.TimeoutExpired) as err:
        return f"'{' '.join(prefix)}' failed: {err}"
    if done.returncode != 0:
        return f"'{' '.join(prefix)}' + veth + raw socket failed: {done.stderr.strip()[-200:]}"
    return None


def _unshare() -> list[str]:
    if _chosen is None:
        why = link_unavailable()
        if why is not None:
            raise RuntimeError(f"no private EtherCAT link: {why}")
    return _chosen


def link_unavailable() -> str | None:
    """Why no namespaced veth link can be made here, or ``None`` when it can."""
    global _chosen
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"no {tool!r} command (util-linux / iproute2)"
    reasons = []
    for prefix in namespaces():
        if prefix[1] == "-n" and os.geteuid() != 0:
            continue  # a plain network namespace needs root
        why = _probe(prefix)
        if why is None:
            _chosen = prefix
            return None
        reasons.append(why)
    return "; ".join(reasons)


def run_on_link(
    path: str, function: str, sim_url: str, serve_args: Sequence[str] = (),
    timeout_s: float = RUN_TIMEOUT_S,
) -> Any:  # fmt: skip
    """``function(MASTER_IFACE, url)`` of the Python file ``path``, run on a private link.

    Raises
    ------
    RuntimeError
        The child failed; its stderr is in the message.
    """
    cmd = [*_unshare(), sys.executable, "-m", "servobench.bench.testing.ethercat_link",
           path, function, sim_url, *serve_args]  # fmt: skip
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    for line in done.stdout.splitlines():
        if line.startswith(RESULT_MARK):
            return json.loads(line[len(RESULT_MARK) :])
    raise RuntimeError(
        f"EtherCAT link child exited {done.returncode} without a result:\n{done.stderr[-4000:]}"
    )


def _wait_for_carrier(iface: str, timeout_s: float = 5.0) -> None:
    """Until the kernel reports the link up (a frame sent before is dropped)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        shown = subprocess.run(["ip", "-o", "link", "show", "dev", iface],
                               capture_output=True, text=True).stdout  # fmt: skip
        if "LOWER_UP" in shown and "state UP" in shown:
            return
        time.sleep(0.01)
    raise RuntimeError(f"{iface} did not come up within {timeout_s} s")


def _child(path: str, function: str, sim_url: str, serve_args: list[str]) -> None:
    from servobench.bench.testing.served import ServedSim

    for cmd in (
        ["ip", "link", "add", MASTER_IFACE, "type", "veth", "peer", "name", SLAVE_IFACE],
        ["ip", "link", "set", MASTER_IFACE, "up"],
        ["ip", "link", "set", SLAVE_IFACE, "up"],
    ):
        subprocess.run(cmd, check=True)
    _wait_for_carrier(MASTER_IFACE)
    _wait_for_carrier(SLAVE_IFACE)
    spec = importlib.util.spec_from_file_location("ethercat_link_target", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    with ServedSim("ethercat", sim_url, ["--iface", SLAVE_IFACE, *serve_args]) as served:
        result = getattr(module, function)(MASTER_IFACE, served.url)
    print(RESULT_MARK + json.dumps(result), flush=True)


if __name__ == "__main__":
    _child(sys.argv[1], sys.argv[2], sys.argv[3], sys.argv[4:])
