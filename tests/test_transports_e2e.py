"""Back to back: `servobench sidbe` over every transport against its served simulated drive.

Each registered real transport is exercised end to end with no hardware:
``servobench serve-sim`` runs in its own process, and the SIDBE procedure
drives it through the full protocol stack (python-can + canopen over the
socketcand hub, pymodbus over loopback TCP and a baud-emulating pty, pyserial
over a pty). The identified linear block must match the plant within 1 %.
"""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from servobench.bench.testing.served import ServedSim
from servobench.drivers.registry import BACKENDS
from servobench.sim_backend.servers.serve import TRANSPORTS

pytestmark = pytest.mark.slow  # sidbe over every served transport, 27 s

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
TRUE_POLE, TRUE_GAIN = -10.0, 1.0
# A short excitation: 4 s period at 50 Hz, so the slowest link (RTU) finishes in seconds.
SIDBE_ARGS = ["--fs", "50", "--periods", "3", "--freqs", "1,2,3,5,8,13", "--amplitude", "3"]
SCHEME = {"canopen": "canopen", "modbus-tcp": "modbus+tcp", "modbus-rtu": "modbus+rtu", "serial": "serial"}


def test_every_served_transport_is_a_registered_drive():
    assert set(SCHEME) == set(TRANSPORTS)
    assert set(SCHEME.values()) <= set(BACKENDS)


@pytest.mark.parametrize("transport", sorted(TRANSPORTS))
def test_sidbe_identifies_the_served_plant(transport, tmp_path):
    with ServedSim(transport, PLANT, clock="lockstep") as served:
        assert served.url.startswith(SCHEME[transport] + "://")
        url = served.url + ("&" if "?" in served.url else "?") + "pace=fast"
        out = subprocess.run(
            [sys.executable, "-m", "servobench", "sidbe", "--drive", url, "--json",
             "--out", str(tmp_path / "run"), *SIDBE_ARGS],
            capture_output=True, text=True, timeout=240,
        )  # fmt: skip
    assert served.returncode == 0, served.stderr
    assert out.returncode == 0, out.stderr
    model = json.loads(out.stdout)
    assert model["pole"] == pytest.approx(TRUE_POLE, rel=0.01)
    assert model["dc_gain"] == pytest.approx(TRUE_GAIN, rel=0.01)
    assert (tmp_path / "run" / "log.csv").is_file()
    assert (tmp_path / "run" / "model.json").is_file()
