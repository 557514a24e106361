"""Table tests of the pure CiA 402 state machine over every state pair."""

from __future__ import annotations

import itertools

import pytest

from servobench.drivers.cia402 import (
    AUTOMATIC,
    CW_DISABLE_VOLTAGE,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    SW_MASK,
    TRANSITIONTABLE,
    CiA402State,
    decode_controlword,
    decode_statusword,
    encode_statusword,
    next_state,
    plan,
    supported_drive_modes,
    supports_mode,
)
from servobench.errors import DriveError, StateTransitionError

S = CiA402State
ALL = list(CiA402State)

# The standard's transitions, written out independently of servobench.drivers.cia402:
# (number, from, command, to).
STANDARD = [
    (2, S.SWITCH_ON_DISABLED, CW_SHUTDOWN, S.READY_TO_SWITCH_ON),
    (3, S.READY_TO_SWITCH_ON, CW_SWITCH_ON, S.SWITCHED_ON),
    (4, S.SWITCHED_ON, CW_ENABLE_OPERATION, S.OPERATION_ENABLED),
    (5, S.OPERATION_ENABLED, CW_SWITCH_ON, S.SWITCHED_ON),
    (6, S.SWITCHED_ON, CW_SHUTDOWN, S.READY_TO_SWITCH_ON),
    (7, S.READY_TO_SWITCH_ON, CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
    (7, S.READY_TO_SWITCH_ON, CW_QUICK_STOP, S.SWITCH_ON_DISABLED),
    (8, S.OPERATION_ENABLED, CW_SHUTDOWN, S.READY_TO_SWITCH_ON),
    (9, S.OPERATION_ENABLED, CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
    (10, S.SWITCHED_ON, CW_QUICK_STOP, S.SWITCH_ON_DISABLED),
    (11, S.OPERATION_ENABLED, CW_QUICK_STOP, S.QUICK_STOP_ACTIVE),
    (12, S.QUICK_STOP_ACTIVE, CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED),
    (15, S.FAULT, CW_FAULT_RESET, S.SWITCH_ON_DISABLED),
    (16, S.QUICK_STOP_ACTIVE, CW_ENABLE_OPERATION, S.OPERATION_ENABLED),
    # "switch on + enable operation" from READY TO SWITCH ON: 3 then 4
    (3, S.READY_TO_SWITCH_ON, CW_ENABLE_OPERATION, S.OPERATION_ENABLED),
]
COMMANDS = [
    CW_DISABLE_VOLTAGE,
    CW_QUICK_STOP,
    CW_SHUTDOWN,
    CW_SWITCH_ON,
    CW_ENABLE_OPERATION,
    CW_FAULT_RESET,
]
EXPECTED = {(src, cw): dst for _, src, cw, dst in STANDARD}


@pytest.mark.parametrize(("state", "command"), list(itertools.product(ALL, COMMANDS)))
def test_next_state_follows_the_standard(state: CiA402State, command: int) -> None:
    expected = EXPECTED.get((state, command), state)  # no transition: stay
    assert next_state(state, command, previous=0) is expected


def test_every_table_entry_is_a_standard_transition() -> None:
    for (src, dst), cw in TRANSITIONTABLE.items():
        assert EXPECTED[(src, cw)] is dst


@pytest.mark.parametrize(
    ("controlword", "expected"),
    [
        (0x0000, CW_DISABLE_VOLTAGE),
        (0x000D, CW_DISABLE_VOLTAGE),  # bit 1 low: disable voltage whatever else
        (0x0002, CW_QUICK_STOP),
        (0x000B, CW_QUICK_STOP),
        (0x0006, CW_SHUTDOWN),
        (0x000E, CW_SHUTDOWN),
        (0x0007, CW_SWITCH_ON),
        (0x000F, CW_ENABLE_OPERATION),
        (0x010F, CW_ENABLE_OPERATION),  # bit 8 (halt) is not a state command
        (0x0080, CW_FAULT_RESET),
        (0x008F, CW_FAULT_RESET),
    ],
)
def test_decode_controlword(controlword: int, expected: int) -> None:
    assert decode_controlword(controlword, previous=0) == expected


def test_fault_reset_needs_a_rising_edge() -> None:
    assert next_state(S.FAULT, 0x80, previous=0x80) is S.FAULT
    assert next_state(S.FAULT, 0x80, previous=0x00) is S.SWITCH_ON_DISABLED
    assert next_state(S.FAULT, 0x0F, previous=0x00) is S.FAULT  # enable does not clear a fault


@pytest.mark.parametrize("state", ALL)
def test_statusword_round_trip(state: CiA402State) -> None:
    word = encode_statusword(state)
    assert decode_statusword(word) is state
    assert decode_statusword(word | 0xFF00) is state  # manufacturer/ high bits don't matter


def test_masks_are_unambiguous_over_all_statuswords() -> None:
    undefined = 0
    for word in range(0x10000):
        matches = [s for s, (mask, value) in SW_MASK.items() if word & mask == value]
        assert len(matches) <= 1, f"0x{word:04X} matches {matches}"
        if matches:
            assert decode_statusword(word) is matches[0]
        else:
            undefined += 1
            with pytest.raises(DriveError):
                decode_statusword(word)
    assert undefined > 0  # e.g. 0x0001 is no state


def _reachable(src: CiA402State, dst: CiA402State) -> bool:
    if src is dst:
        return True
    if dst in (S.NOT_READY_TO_SWITCH_ON, S.FAULT_REACTION_ACTIVE):
        return False
    if dst is S.FAULT:
        return src is S.FAULT_REACTION_ACTIVE
    return True


@pytest.mark.parametrize(("src", "dst"), list(itertools.product(ALL, ALL)))
def test_plan_reaches_every_reachable_pair(src: CiA402State, dst: CiA402State) -> None:
    if not _reachable(src, dst):
        with pytest.raises(StateTransitionError):
            plan(src, dst)
        return
    steps = plan(src, dst)
    state, previous = src, 0
    for step in steps:
        if step.controlword is None:
            assert AUTOMATIC[state] is step.next_state
            state = step.next_state
            continue
        state = next_state(state, step.controlword, previous)
        previous = step.controlword
        assert state is step.next_state, f"{step} from {src} led to {state}"
    assert state is dst
    if src is dst:
        assert steps == []


@pytest.mark.parametrize(
    ("src", "dst", "controlwords"),
    [
        (S.SWITCH_ON_DISABLED, S.OPERATION_ENABLED, [0x06, 0x07, 0x0F]),  # 2, 3, 4
        (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED, [0x00]),  # 9
        (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, [0x02]),  # 11
        (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED, [0x0F]),  # 16
        (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED, [0x00]),  # 12
        (S.FAULT, S.OPERATION_ENABLED, [0x80, 0x06, 0x07, 0x0F]),  # 15, 2, 3, 4
        (S.FAULT_REACTION_ACTIVE, S.SWITCH_ON_DISABLED, [None, 0x80]),  # 14, 15
        (S.NOT_READY_TO_SWITCH_ON, S.READY_TO_SWITCH_ON, [None, 0x06]),  # 1, 2
        (S.SWITCHED_ON, S.QUICK_STOP_ACTIVE, [0x0F, 0x02]),  # 4, 11
    ],
)
def test_plan_is_the_shortest_standard_path(
    src: CiA402State, dst: CiA402State, controlwords: list[int | None]
) -> None:
    assert [step.controlword for step in plan(src, dst)] == controlwords


# 0x6502 values real drives publish: ZeroErr eDriver 909 (its EDS), an MD80
# controller 0x00030287 (its object dictionary: PP, VL, PV, CSP, CST and two
# manufacturer-specific modes in bits 16 and 17).
@pytest.mark.parametrize(
    ("supported", "offered", "absent"),
    [
        (909, {1, 3, 4, 8, 9, 10}, {2, 6, 7}),
        (0x00030287, {1, 2, 3, 8, 10}, {4, 6, 7, 9}),
    ],
)
def test_supported_drive_modes_of_published_drives(supported, offered, absent) -> None:
    assert {m for m in offered | absent if supports_mode(supported, m)} == offered
    assert supported_drive_modes(sorted(offered)) == supported & 0x3FF
    assert not supports_mode(supported, 0) and not supports_mode(supported, 11)
