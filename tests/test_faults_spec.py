"""The --fault grammar, the injector and the per-transport hooks, in-process."""

from __future__ import annotations

import os
import select
import time

import pytest

from servobench.errors import DriveConfigError
from servobench.sim_backend.device import GENERIC_FAULT, PowerState, SimulatedDevice
from servobench.sim_backend.faults.can import CanFaultHook, emcy_frame
from servobench.sim_backend.faults.injector import FaultInjector
from servobench.sim_backend.faults.modbus import corrupt_crc
from servobench.sim_backend.faults.serial import STRAY_LINE, SerialFaultHook
from servobench.sim_backend.faults.spec import (
    KINDS,
    LINK_TRANSPORTS,
    TRANSPORTS,
    FaultSpec,
    kinds_for,
    parse_plan,
)
from servobench.sim_backend.faults.state import StateReporter, snapshot
from servobench.sim_backend.physics.plant import PlantParams
from servobench.sim_backend.servers.pty_link import PtyLink


def device() -> SimulatedDevice:
    return SimulatedDevice(PlantParams(M=0.1, B=1.0, coulomb_pos=0.5, coulomb_neg=0.4))


@pytest.mark.parametrize(
    ("text", "transport", "specs"),
    [
        ("drop@5", "canopen", [("drop", 5, None)]),
        ("delay@7:30 ; dup@9", "serial", [("delay", 7, 30), ("dup", 9, None)]),
        ("fault@3", "modbus-rtu", [("fault", 3, GENERIC_FAULT)]),
        ("fault@3:0x2310", "canopen", [("fault", 3, 0x2310)]),
        ("busoff@4", "canopen", [("busoff", 4, 200)]),
        ("emcy@4", "canopen", [("emcy", 4, 0xFF00)]),
        ("exception@2", "modbus-tcp", [("exception", 2, 4)]),
        ("busy@2", "modbus-tcp", [("exception", 2, 6)]),  # old spelling
        ("silence@2", "modbus-tcp", [("timeout", 2, None)]),
        ("silence@2", "canopen", [("drop", 2, None)]),
        ("silence@2", "serial", [("drop", 2, None)]),
        ("delay@5:10;freeze@5;fault@5", "serial",
         [("freeze", 5, None), ("fault", 5, GENERIC_FAULT), ("delay", 5, 10)]),
        ("", "serial", []),
    ],
)  # fmt: skip
def test_parse(text: str, transport: str, specs: list) -> None:
    plan = parse_plan(text, transport)
    assert [(s.kind, s.cycle, s.arg) for s in plan.specs] == specs


def test_settings_and_several_strings() -> None:
    plan = parse_plan(["reject_mode=10", "ignore_mode=4;drop@3"], "canopen")
    assert plan.setting("reject_mode") == {10} and plan.setting("ignore_mode") == {4}
    assert [str(s) for s in plan.at(3)] == ["drop@3"] and plan.at(4) == ()


@pytest.mark.parametrize(
    ("text", "transport", "why"),
    [
        ("drop", "canopen", "no @N"),
        ("drop@0", "canopen", "not an integer >= 1"),
        ("drop@x", "canopen", "not an integer >= 1"),
        ("drop@-3", "canopen", "not an integer >= 1"),
        ("boom@3", "canopen", "unknown kind 'boom'"),
        ("crc@3", "modbus-tcp", "crc applies to modbus-rtu only"),
        ("garble@3", "canopen", "garble applies to serial only"),
        ("busy@3", "serial", "busy does not apply to serial"),
        ("delay@3", "serial", "delay needs :MS"),
        ("delay@3:-1", "serial", "outside 0..60000"),
        ("drop@3:5", "canopen", "drop takes no argument"),
        ("busy@3:5", "modbus-tcp", "busy takes no argument"),
        ("exception@3:9", "modbus-tcp", "no Modbus exception code"),
        ("fault@3:0x10000", "serial", "outside 0x0001..0xFFFF"),
        ("fault@3:abc", "serial", "argument 'abc' is not an integer"),
        ("drop@3;dup@3", "canopen", "cycle 3 already has 'drop@3'"),
        ("reject_mode=10", "serial", "reject_mode does not apply to serial"),
        ("reject_mode=x", "canopen", "needs a non-negative integer"),
    ],
)
def test_bad_items_name_the_item_and_why(text: str, transport: str, why: str) -> None:
    with pytest.raises(DriveConfigError) as err:
        parse_plan(text, transport)
    message = str(err.value)
    assert "bad --fault" in message and why in message and "KIND@N" in message
    assert len(message.splitlines()) == 1


def test_every_transport_has_kinds_and_every_kind_a_transport() -> None:
    for transport in TRANSPORTS + LINK_TRANSPORTS:
        assert {"fault", "freeze", "delay"} <= set(kinds_for(transport))
    everywhere = set(TRANSPORTS + LINK_TRANSPORTS)
    assert all(k.transports <= everywhere and k.summary for k in KINDS.values())


def test_injector_fault_and_freeze() -> None:
    dev = device()
    inj = FaultInjector(dev, parse_plan("fault@4:0x5441;freeze@2;delay@3:1", "serial"))
    dev.enable()
    dev.set_command(2.0)
    wire = [inj.next_cycle() for _ in range(1)]
    s1 = inj.step()
    assert wire == [()] and s1.velocity == 0.0
    assert inj.next_cycle() == ()
    s2 = inj.step()  # the frozen sample itself is real
    assert inj.next_cycle() == (FaultSpec("delay", 3, 1, "delay@3:1"),)
    s3 = inj.step()
    assert (s3.velocity, s3.position) == (s2.velocity, s2.position) and s3.t_s > s2.t_s
    assert dev.plant.state.v > s2.velocity  # the plant runs on, the sensor does not
    assert (inj.sample().velocity, inj.sample().position) == (s2.velocity, s2.position)
    inj.next_cycle()
    assert dev.state is PowerState.FAULT and dev.fault_code == 0x5441
    assert [f["kind"] for f in inj.record()] == ["freeze", "delay", "fault"]


def test_serial_hook() -> None:
    hook, raw, term = SerialFaultHook(), b"0.500000 1.250000\r\n", b"\r\n"

    def spec(kind: str, arg: int | None = None) -> tuple[FaultSpec, ...]:
        return (FaultSpec(kind, 1, arg),)

    assert hook.reply((), raw, term).data == raw
    assert hook.reply(spec("drop"), raw, term).data == b""
    assert hook.reply(spec("dup"), raw, term).data == raw + raw
    assert hook.reply(spec("delay", 25), raw, term).delay_s == 0.025
    assert hook.reply(spec("truncate"), raw, term).data == b"0.500000\r\n"
    garbled = hook.reply(spec("garble"), raw, term).data
    assert garbled.endswith(term) and garbled != raw and len(garbled) == len(raw)
    mixed = hook.reply(spec("interleave"), raw, term).data
    assert mixed == b"0.500000" + STRAY_LINE + term + b" 1.250000" + term


def test_can_hook_transmissions_and_bus_off() -> None:
    now = [100.0]
    hook = CanFaultHook(FaultInjector(device(), parse_plan("", "canopen")), lambda: now[0])
    frames = [(0x182, b"\x01" * 8), (0x282, b"\x02" * 8)]
    assert hook.transmissions((), frames, 2)[0].frames == tuple(frames)
    assert hook.transmissions((FaultSpec("drop", 1),), frames, 2) == []
    assert hook.transmissions((FaultSpec("dup", 1),), frames, 2)[0].frames == tuple(frames) * 2
    late = hook.transmissions((FaultSpec("delay", 1, 40),), frames, 2)[0]
    assert late.delay_s == 0.04 and late.frames == tuple(frames)
    warned = hook.transmissions((FaultSpec("emcy", 1, 0x4210),), frames, 2)[0].frames
    assert warned[0] == emcy_frame(2, 0x4210, 1) == (0x82, b"\x10\x42\x01\x00\x00\x00\x00\x00")
    hook.bus_off(FaultSpec("busoff", 1, 200))
    assert hook.muted() and not hook.recovered()
    now[0] += 0.25
    assert not hook.muted() and hook.recovered() and not hook.recovered()


def test_crc_tamper_on_the_rtu_link() -> None:
    assert corrupt_crc(b"\x01\x03\x02\x00\x05\x78\x47") == b"\x01\x03\x02\x00\x05\x78\x46"
    with PtyLink(baud=115200, frame_gap_s=1e-3) as link:
        a = os.open(link.a_path, os.O_RDWR | os.O_NOCTTY)
        b = os.open(link.b_path, os.O_RDWR | os.O_NOCTTY)
        try:
            link.tamper_next(corrupt_crc)
            for expected in (b"\x01\x02\x02", b"\x01\x02\x03"):  # tampered once, then clean
                os.write(b, b"\x01\x02\x03")
                assert select.select([a], [], [], 1.0)[0]
                time.sleep(0.005)
                assert os.read(a, 16) == expected
        finally:
            os.close(a)
            os.close(b)


def test_state_report_changes_and_final(tmp_path) -> None:
    dev = device()
    inj = FaultInjector(dev, parse_plan("fault@2", "modbus-tcp"))
    path = tmp_path / "state.json"
    reporter = StateReporter(dev, inj, path)
    assert path.exists()  # written before the server announces itself
    reporter.start()
    dev.enable()
    time.sleep(0.1)
    inj.next_cycle()
    inj.step()
    inj.next_cycle()  # faults
    reporter.finish()
    import json

    report = json.loads(path.read_text())
    assert report["final"] and report["state"] == "fault" and report["fault_code"] == GENERIC_FAULT
    assert [h["state"] for h in report["history"]] == ["disabled", "enabled", "fault"]
    assert report["cycles"] == 2 and report["faults_injected"][0]["kind"] == "fault"
    assert report["torque_off"] and report["command"] == 0.0
    assert snapshot(dev, None)["cycles"] is None


def test_frozen_check_spares_a_coarse_encoder_and_catches_a_frozen_one() -> None:
    from servobench.bench.run.runner import FeedbackCheck
    from servobench.errors import DriveError

    check = FeedbackCheck(frozen_cycles=100, dt_s=1e-3)
    for k in range(2000):  # creeping at 0.05 units/s on a 0.01-unit encoder: x steps every 200
        check.check(k * 1e-3, 0.3, 0.05, 0.01 * (k // 200))
    check = FeedbackCheck(frozen_cycles=100, dt_s=1e-3)
    with pytest.raises(DriveError, match="bit-identical for 100 cycles while the drive reports"):
        for k in range(2000):  # moving at 1 unit/s (steps of 1e-3), then the sensor stops
            kk = min(k, 500)
            check.check(k * 1e-3, 1.0, 1.0, kk * 1e-3)
    assert k == 600
    check = FeedbackCheck(frozen_cycles=50, breakaway=0.5, dt_s=1e-3)
    with pytest.raises(DriveError, match="breakaway 0.5"):  # stuck at rest while pushed hard
        for k in range(100):
            check.check(k * 1e-3, 0.8, 0.0, 0.0)
