"""``servobench commission --dry-run`` writes nothing to the drive, counted from the peer's side.

EtherCAT: the frames on the master's end of a private veth link, captured
with a raw socket of the test: no CoE SDO download request, no AL control
request (0x0120) for SAFE-OP or OP. CANopen: the frames on the served
drive's CAN hub: no SDO download (client command specifier 0 or 1) and no
NMT command. Modbus TCP: the requests through a forwarding proxy: no write
function code (5, 6, 15, 16, 23). Each also counts a plain open of the same
drive, which writes, so that a counter that sees nothing fails.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import pytest

from servobench.bench.cli import main
from servobench.bench.testing.ethercat_link import link_unavailable, run_on_link
from servobench.drivers.registry import open_drive

PLANT = "sim://?M=0.1&B=1&fc_pos=0.5&fc_neg=0.4"
CONFIG = """
[limits]
max_u = 2.0
max_v = 20.0
xmin = -inf
xmax = inf
"""
#: Modbus function codes that write (coils, registers, read/write multiple).
MODBUS_WRITES = frozenset({5, 6, 15, 16, 23})
#: EtherCAT commands that write a slave's memory (auto-increment, configured, broadcast).
ECAT_WRITES = frozenset({2, 3, 5, 6, 8, 9})
AL_CONTROL, SAFE_OP, OP = 0x0120, 0x04, 0x08
#: Linux's SO_RCVBUFFORCE (asm-generic/socket.h), which Python's socket module does not name.
SO_RCVBUFFORCE = 33


def _dry_run(url: str, tmp: str) -> subprocess.CompletedProcess:
    config = Path(tmp) / "bench.toml"
    config.write_text(CONFIG)
    return subprocess.run(
        [sys.executable, "-m", "servobench", "commission", "--drive", url, "--dry-run", "--yes",
         "--config", str(config), "--out", tmp + "/record"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip


# -------------------------------------------------------------------- EtherCAT
def ethercat_writes(frame: bytes) -> tuple[int, int]:
    """(CoE SDO download requests, AL control requests for SAFE-OP or OP) in one frame."""
    if len(frame) < 16 or frame[12:14] != b"\x88\xa4":
        return 0, 0
    end = 16 + (int.from_bytes(frame[14:16], "little") & 0x7FF)
    sdo = al = 0
    off = 16
    while off + 12 <= end:
        cmd, ado = frame[off], int.from_bytes(frame[off + 4 : off + 6], "little")
        word = int.from_bytes(frame[off + 6 : off + 8], "little")
        data = frame[off + 10 : off + 10 + (word & 0x7FF)]
        if cmd in ECAT_WRITES:
            if ado == AL_CONTROL and data and data[0] & 0x0F in (SAFE_OP, OP):
                al += 1
            # a mailbox write: header (6), CoE header with service 2 (SDO request), then the
            # SDO command, whose client command specifier 1 is a download request
            if ado >= 0x1000 and len(data) >= 9 and data[5] & 0x0F == 3 and data[7] >> 4 == 2:
                sdo += data[8] >> 5 == 1
        off += 10 + (word & 0x7FF) + 2
        if not word & 0x8000:
            break
    return sdo, al


class FrameCounter:
    """Counts the writes in the frames the master sends on ``iface`` while it runs."""

    def __init__(self, iface: str) -> None:
        # ETH_P_ALL: only such taps see the frames this host sends
        self.sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0003))
        # a deep buffer: each queued frame costs ~1 kB of it, and this thread waits for the GIL
        # while the master streams (the default ~200 kB overflowed now and then)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 16 << 20)
        except PermissionError:  # a user namespace: as deep as rmem_max allows
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        self.sock.bind((iface, 0))
        self.sock.settimeout(0.05)
        self.counts = {"frames": 0, "sdo_downloads": 0, "al_safe_op_or_op": 0}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        # Each datagram goes out from the master and comes back from the slave: counted both
        # ways, and each kind as the larger of the two (a tap on a busy machine can miss a frame
        # in one direction; it has never been seen to miss both).
        out, back = [0, 0, 0], [0, 0, 0]  # EtherCAT frames are broadcast: the answers too
        while not self._stop.is_set():
            try:
                frame, addr = self.sock.recvfrom(2048)
            except TimeoutError:
                continue
            way = out if addr[2] == socket.PACKET_OUTGOING else back
            sdo, al = ethercat_writes(frame)
            way[0] += 1
            way[1] += sdo
            way[2] += al
        self.counts = {"frames": max(out[0], back[0]), "sdo_downloads": max(out[1], back[1]),
                       "al_safe_op_or_op": max(out[2], back[2])}  # fmt: skip

    def __enter__(self) -> FrameCounter:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        time.sleep(0.1)
        self._stop.set()
        self._thread.join(2)
        self.sock.close()


def link_dry_run(iface: str, url: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp, FrameCounter(iface) as dry:
        done = _dry_run(url, tmp)
    with FrameCounter(iface) as plain, open_drive(url) as drive:  # the control: what a run does
        drive.bus.sdo_write(0x6060, 0, bytes([10]))  # cyclic synchronous torque, as a run sets it
        drive.set_cycle(0.002)  # back to PRE-OP for the cycle time, then SAFE-OP and OP again
        drive.enable()
        drive.disable()
    return {"rc": done.returncode, "stdout": done.stdout, "stderr": done.stderr[-2000:],
            "dry": dry.counts, "plain": plain.counts}  # fmt: skip


def test_ethercat_dry_run_writes_nothing() -> None:
    why = link_unavailable()
    if why is not None:
        pytest.fail(f"no private EtherCAT link: {why}")
    out = run_on_link(__file__, "link_dry_run", PLANT, ["--clock", "lockstep"])
    assert out["rc"] == 0, out["stderr"]
    assert "Traceback" not in out["stderr"]
    # a plain open writes only what differs from the slave's values, so the control writes for sure
    assert out["plain"]["sdo_downloads"] >= 1 and out["plain"]["al_safe_op_or_op"] >= 1, out[
        "plain"
    ]
    assert out["dry"]["frames"] > 10  # it did talk to the slave
    assert out["dry"]["sdo_downloads"] == 0 and out["dry"]["al_safe_op_or_op"] == 0, out["dry"]


# --------------------------------------------------------------------- CANopen
def test_canopen_dry_run_writes_nothing(tmp_path) -> None:
    from servobench.bench.testing.served_canopen import raw_bus, served

    with served() as (_device, url):
        node = int(url.split("node=")[1].split("&")[0])
        frames: list = []
        with raw_bus(url) as bus:
            stop = threading.Event()

            def listen() -> None:
                while not stop.is_set():
                    msg = bus.recv(0.05)
                    if msg is not None:
                        frames.append((msg.arbitration_id, bytes(msg.data)))

            thread = threading.Thread(target=listen, daemon=True)
            thread.start()
            try:
                (tmp_path / "bench.toml").write_text(CONFIG)
                rc = main(["commission", "--drive", url, "--dry-run", "--yes", "--config",
                           str(tmp_path / "bench.toml"), "--out", str(tmp_path / "record")])  # fmt: skip
                time.sleep(0.2)
                dry = list(frames)
                with open_drive(url):  # the control: a plain open writes and starts the node
                    pass
                time.sleep(0.2)
            finally:
                stop.set()
                thread.join(2)
        plain = frames[len(dry) :]

    def count(seen: list) -> dict:
        sdo = [d for i, d in seen if i == 0x600 + node and d and d[0] >> 5 in (0, 1)]
        nmt = [d for i, d in seen if i == 0x000]
        uploads = [d for i, d in seen if i == 0x600 + node and d and d[0] >> 5 == 2]
        return {"sdo_downloads": len(sdo), "nmt": len(nmt), "uploads": len(uploads)}

    assert rc == 0
    assert count(plain)["sdo_downloads"] > 5 and count(plain)["nmt"] >= 1, count(plain)
    assert count(dry)["uploads"] > 5  # it did read the drive
    assert count(dry)["sdo_downloads"] == 0 and count(dry)["nmt"] == 0, count(dry)


# ---------------------------------------------------------------------- Modbus
class ModbusProxy:
    """A TCP proxy in front of a Modbus TCP server that counts the requests' function codes."""

    def __init__(self, host: str, port: int) -> None:
        self.upstream = (host, port)
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.codes: list[int] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(self.upstream)
            threading.Thread(target=self._pipe, args=(client, server, True), daemon=True).start()
            threading.Thread(target=self._pipe, args=(server, client, False), daemon=True).start()

    def _pipe(self, src: socket.socket, dst: socket.socket, requests: bool) -> None:
        buf = b""
        try:
            while data := src.recv(4096):
                dst.sendall(data)
                if not requests:
                    continue
                buf += data
                while len(buf) >= 8 and len(buf) >= 6 + (n := struct.unpack_from(">H", buf, 4)[0]):
                    self.codes.append(buf[7])
                    buf = buf[6 + n :]
        except OSError:
            pass
        finally:
            for s in (src, dst):
                with contextlib.suppress(OSError):
                    s.shutdown(socket.SHUT_RDWR)

    def close(self) -> None:
        self.listener.close()


def test_modbus_dry_run_writes_nothing(tmp_path) -> None:
    from servobench.bench.testing.served_modbus import host_port, served_modbus

    with served_modbus("modbus-tcp") as (_device, url):
        host, port = host_port(url)
        proxy = ModbusProxy(host, port)
        proxied = url.replace(f"{host}:{port}", f"127.0.0.1:{proxy.port}")
        try:
            (tmp_path / "bench.toml").write_text(CONFIG)
            rc = main(["commission", "--drive", proxied, "--dry-run", "--yes", "--config",
                       str(tmp_path / "bench.toml"), "--out", str(tmp_path / "record")])  # fmt: skip
            time.sleep(0.1)
            dry = list(proxy.codes)
            with open_drive(proxied):  # the control: a plain open sets the drive's watchdog
                pass
            time.sleep(0.1)
            plain = proxy.codes[len(dry) :]
        finally:
            proxy.close()
    assert rc == 0
    assert any(c in MODBUS_WRITES for c in plain), plain
    assert dry and not [c for c in dry if c in MODBUS_WRITES], dry
