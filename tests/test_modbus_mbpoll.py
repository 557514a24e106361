"""Debian's ``mbpoll`` (libmodbus, not servobench) against the served drive, over TCP and RTU.

``mbpoll`` is a peer of the test command (``tests/peers.py``), which installs it
as root and otherwise stops before any test runs: these tests never skip. References are 0-based (``-0``): the
fault register is PDU address 33 (0x21) in ``servobench-sim.toml``.
"""

from __future__ import annotations

import shutil
import subprocess

import pytest

from servobench.bench.testing.served_modbus import host_port, rtu_path
from servobench.bench.testing.served_modbus import served_modbus as served
from servobench.sim_backend.device import PowerState

MBPOLL = shutil.which("mbpoll")


def mbpoll(url: str, *args: str, values: tuple[str, ...] = ()) -> subprocess.CompletedProcess[str]:
    """Run mbpoll once (``-1``) against the served drive at ``url``."""
    assert MBPOLL, "mbpoll is not installed: the test command installs it as root (tests/peers.py)"
    if url.startswith("modbus+tcp"):
        host, port = host_port(url)
        link = ["-m", "tcp", "-p", str(port)]
        target = host
    else:
        link = ["-m", "rtu", "-b", "115200", "-P", "none"]
        target = rtu_path(url)
    return subprocess.run(
        [MBPOLL, *link, "-1", "-o", "0.5", *args, target, *values],
        capture_output=True, text=True, timeout=20,
    )  # fmt: skip


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu"])
def test_mbpoll_reads_writes_and_gets_the_exceptions_the_spec_names(transport):
    with served(transport) as (device, url):
        out = mbpoll(url, "-a", "1", "-0", "-r", "33")
        assert out.returncode == 0 and "[33]: \t0" in out.stdout, out.stderr
        out = mbpoll(url, "-a", "1", "-0", "-r", "1", values=("300",))  # watchdog = 300 ms
        assert out.returncode == 0, out.stderr
        assert device.watchdog_s == pytest.approx(0.3)
        out = mbpoll(url, "-a", "1", "-0", "-r", "0", values=("1",))  # control: enable
        assert out.returncode == 0 and device.state is PowerState.ENABLED, out.stderr
        out = mbpoll(url, "-a", "1", "-0", "-r", "36", "-c", "2", "-t", "4:int", "-B")
        assert out.returncode == 0 and "[36]: \t0" in out.stdout, out.stderr  # velocity, int32
        out = mbpoll(url, "-a", "1", "-0", "-t", "0", "-r", "0")  # a coil: the drive has none
        assert out.returncode != 0 and "Illegal function" in out.stderr
        out = mbpoll(url, "-a", "1", "-0", "-r", "768")  # 0x0300: no register there
        assert out.returncode != 0 and "Illegal data address" in out.stderr
        out = mbpoll(url, "-a", "7", "-0", "-r", "33")  # a unit that is not there
        assert out.returncode != 0
        if transport == "modbus-tcp":  # the gateway exception 0x0B
            assert "Target device failed to respond" in out.stderr
        else:  # silence on the line
            assert "timed out" in out.stderr


def test_mbpoll_report_slave_id_on_rtu():
    with served("modbus-rtu") as (_, url):
        out = mbpoll(url, "-a", "1", "-u")
        assert out.returncode == 0, out.stderr
        assert "Id    : 0x01" in out.stdout and "Status: Off" in out.stdout
        assert "servobench simulated DC servo" in out.stdout
