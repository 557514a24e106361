"""The CiA 402 power state machine as data, shared by host and drive.

Pure: no I/O. The host side (:mod:`servobench.drivers.canopen.drive`) decodes statuswords
with :func:`decode_statusword` and walks :func:`plan`; the simulated drive
(:mod:`servobench.sim_backend.servers.canopen.drive`) steps :func:`next_state` on every controlword
it receives. Both read the same :data:`SW_MASK` and :data:`TRANSITIONTABLE`,
so they agree by construction.

State diagram (CiA 402; transition numbers in brackets)::

                 [1]              [2]              [3]            [4]
    NOT READY ------> SWITCH ON -----> READY TO -------> SWITCHED -----> OPERATION --[11]--> QUICK STOP
    TO SWITCH ON      DISABLED  <----- SWITCH ON <------ ON       <----- ENABLED   <-[16]--- ACTIVE
                        ^  ^  ^   [7]      ^      [6]    |         [5]   |  |                  |
                        |  |  +------------|------[10]---+               |  |                  |
                        |  +---------------|------[9]--------------------+  |                  |
                        |                  +------[8]-----------------------+                  |
                        +-----------------------------[12]-----------------------------------+
                        +--[15]-- FAULT <--[14]-- FAULT REACTION ACTIVE <--[13]-- any state

Controlword bits (0x6040): 0 switch on, 1 enable voltage, 2 quick stop
(active low), 3 enable operation, 7 fault reset (acts on the rising edge).
Statusword bits (0x6041) used for the state: 0 ready to switch on,
1 switched on, 2 operation enabled, 3 fault, 5 quick stop (active low),
6 switch on disabled.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from enum import Enum
from typing import NamedTuple

from servobench.errors import DriveError, StateTransitionError, UsageError


class CiA402State(Enum):
    """The eight states of the CiA 402 power state machine."""

    NOT_READY_TO_SWITCH_ON = "NOT READY TO SWITCH ON"
    SWITCH_ON_DISABLED = "SWITCH ON DISABLED"
    READY_TO_SWITCH_ON = "READY TO SWITCH ON"
    SWITCHED_ON = "SWITCHED ON"
    OPERATION_ENABLED = "OPERATION ENABLED"
    QUICK_STOP_ACTIVE = "QUICK STOP ACTIVE"
    FAULT_REACTION_ACTIVE = "FAULT REACTION ACTIVE"
    FAULT = "FAULT"


S = CiA402State

#: Statusword ``(mask, value)`` that identifies each state (CiA 402 table 30).
SW_MASK: dict[CiA402State, tuple[int, int]] = {
    S.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),  # xxxx xxxx x0xx 0000
    S.SWITCH_ON_DISABLED: (0x4F, 0x40),  # xxxx xxxx x1xx 0000
    S.READY_TO_SWITCH_ON: (0x6F, 0x21),  # xxxx xxxx x01x 0001
    S.SWITCHED_ON: (0x6F, 0x23),  # xxxx xxxx x01x 0011
    S.OPERATION_ENABLED: (0x6F, 0x27),  # xxxx xxxx x01x 0111
    S.QUICK_STOP_ACTIVE: (0x6F, 0x07),  # xxxx xxxx x00x 0111
    S.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),  # xxxx xxxx x0xx 1111
    S.FAULT: (0x4F, 0x08),  # xxxx xxxx x0xx 1000
}

# Device control commands: the controlword the host sends for each.
CW_DISABLE_VOLTAGE = 0x0000
CW_QUICK_STOP = 0x0002
CW_SHUTDOWN = 0x0006
CW_SWITCH_ON = 0x0007  # also "disable operation"
CW_ENABLE_OPERATION = 0x000F  # also "switch on + enable operation"
CW_FAULT_RESET = 0x0080  # acts on the rising edge of bit 7

#: Controlword bit 7, fault reset.
CW_FAULT_RESET_BIT = 0x0080

#: ``(from, to) -> controlword`` the host sends for each commanded transition.
TRANSITIONTABLE: dict[tuple[CiA402State, CiA402State], int] = {
    (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON): CW_SHUTDOWN,  # 2
    (S.READY_TO_SWITCH_ON, S.SWITCHED_ON): CW_SWITCH_ON,  # 3
    (S.SWITCHED_ON, S.OPERATION_ENABLED): CW_ENABLE_OPERATION,  # 4
    (S.OPERATION_ENABLED, S.SWITCHED_ON): CW_SWITCH_ON,  # 5 (disable operation)
    (S.SWITCHED_ON, S.READY_TO_SWITCH_ON): CW_SHUTDOWN,  # 6
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,  # 7
    (S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON): CW_SHUTDOWN,  # 8
    (S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,  # 9
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,  # 10
    (S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE): CW_QUICK_STOP,  # 11
    (S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED): CW_DISABLE_VOLTAGE,  # 12
    (S.FAULT, S.SWITCH_ON_DISABLED): CW_FAULT_RESET,  # 15
    (S.QUICK_STOP_ACTIVE, S.OPERATION_ENABLED): CW_ENABLE_OPERATION,  # 16
}

#: Other commands the standard accepts for the same transition (drive side only).
ALSO_TRIGGERED_BY: dict[tuple[CiA402State, CiA402State], tuple[int, ...]] = {
    (S.READY_TO_SWITCH_ON, S.SWITCHED_ON): (CW_ENABLE_OPERATION,),  # 3, then 4 at once
    (S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED): (CW_QUICK_STOP,),  # 7
    (S.SWITCHED_ON, S.SWITCH_ON_DISABLED): (CW_QUICK_STOP,),  # 10
}

#: Transitions the drive makes by itself: ``from -> to``.
AUTOMATIC: dict[CiA402State, CiA402State] = {
    S.NOT_READY_TO_SWITCH_ON: S.SWITCH_ON_DISABLED,  # 1, after self-test
    S.FAULT_REACTION_ACTIVE: S.FAULT,  # 14, when the fault reaction is done
}

#: States in which a quick stop has done its work (CiA 402 0x605A): the drive no longer
#: follows the host's command. Option codes 0-4 end in SWITCH ON DISABLED (1-4 through
#: QUICK STOP ACTIVE while they brake), 5-8 stay in QUICK STOP ACTIVE.
QUICK_STOPPED: frozenset[CiA402State] = frozenset({S.SWITCH_ON_DISABLED, S.QUICK_STOP_ACTIVE})


def quick_stop_end(option_code: int | None) -> CiA402State:
    """The state a quick stop ends in by the drive's quick stop option code 0x605A.

    0-4 (disable drive function; stop on the slow-down ramp, the quick-stop
    ramp, at the current or the voltage limit): SWITCH ON DISABLED; 5-8 (the
    same four, then staying put): QUICK STOP ACTIVE. ``None`` (the drive has no
    0x605A) and the manufacturer's negative codes: SWITCH ON DISABLED, the
    standard's default behaviour; either state of :data:`QUICK_STOPPED` still
    counts as stopped.
    """
    if option_code is not None and 5 <= option_code <= 8:
        return S.QUICK_STOP_ACTIVE
    return S.SWITCH_ON_DISABLED


#: How long each step of :func:`stop_axis` may take [s].
STOP_STEP_S = 1.0


def stop_axis(
    await_state: Callable[[int, CiA402State], CiA402State], option_code: int | None, who: str,
    step_s: float = STOP_STEP_S,
) -> tuple[CiA402State, str]:
    """Stop an enabled axis the CiA 402 way, on any transport: the state reached and a remark.

    The quick stop (transition 11) ends as 0x605A says (:func:`quick_stop_end`);
    either state of :data:`QUICK_STOPPED` counts as stopped (remark ``""``). A
    drive still enabled after the quick stop gets disable voltage (transitions
    9 and 12) and must reach SWITCH ON DISABLED; the remark then says it did not
    honour the quick stop. ``await_state(controlword, target)`` sends the
    controlword and returns the state reached by ``target`` or its deadline
    (``step_s`` [s]); ``who`` names the drive in messages.

    Raises
    ------
    StateTransitionError
        The axis stayed enabled after disable voltage too.
    """
    state = await_state(CW_QUICK_STOP, quick_stop_end(option_code))
    if state in QUICK_STOPPED:
        return state, ""
    seen = state
    state = await_state(CW_DISABLE_VOLTAGE, S.SWITCH_ON_DISABLED)
    option = "none" if option_code is None else str(option_code)
    if state is not S.SWITCH_ON_DISABLED:
        raise StateTransitionError(
            f"{who} did not stop: it stayed in {seen.value} after the quick stop (0x605A = {option}) "
            f"and in {state.value} after disable voltage, {step_s} s each"
        )
    return state, (f"stopped by disable voltage: the drive did not honour the quick stop "
                   f"(0x605A = {option}; it stayed in {seen.value} for {step_s} s)")  # fmt: skip


#: Human-readable names of the device control commands, for messages.
COMMAND_NAMES: dict[int, str] = {
    CW_DISABLE_VOLTAGE: "disable voltage",
    CW_QUICK_STOP: "quick stop",
    CW_SHUTDOWN: "shutdown",
    CW_SWITCH_ON: "switch on",
    CW_ENABLE_OPERATION: "enable operation",
    CW_FAULT_RESET: "fault reset",
}


#: Modes of operation (0x6060) servobench uses.
MODE_PROFILE_TORQUE = 4
MODE_CSP = 8  # cyclic synchronous position
MODE_CST = 10  # cyclic synchronous torque
#: The bit of 0x6502 (supported drive modes) that announces each standard mode.
SUPPORTED_MODE_BITS: dict[int, int] = {
    1: 0,  # profile position
    2: 1,  # velocity
    3: 2,  # profile velocity
    4: 3,  # profile torque
    6: 5,  # homing
    7: 6,  # interpolated position
    8: 7,  # cyclic synchronous position
    9: 8,  # cyclic synchronous velocity
    10: 9,  # cyclic synchronous torque
}


def supports_mode(supported_drive_modes: int, mode: int) -> bool:
    """True when 0x6502 ``supported_drive_modes`` announces mode of operation ``mode``."""
    bit = SUPPORTED_MODE_BITS.get(mode)
    return bit is not None and bool(supported_drive_modes >> bit & 1)


def supported_drive_modes(modes: list[int] | tuple[int, ...]) -> int:
    """The 0x6502 value announcing ``modes`` (drive side)."""
    return sum(1 << SUPPORTED_MODE_BITS[m] for m in set(modes))


class Step(NamedTuple):
    """One step of a :func:`plan`: send ``controlword`` (``None``: wait), expect ``next_state``."""

    controlword: int | None
    next_state: CiA402State


def decode_statusword(statusword: int) -> CiA402State:
    """The state a statusword (0x6041) reports.

    Raises
    ------
    DriveError
        When the bits match no CiA 402 state.
    """
    for state, (mask, value) in SW_MASK.items():
        if statusword & mask == value:
            return state
    raise DriveError(f"statusword 0x{statusword:04X} matches no CiA 402 state")


def encode_statusword(
    state: CiA402State, *, remote: bool = True, target_reached: bool = False
) -> int:
    """The statusword a drive reports in ``state`` (drive side).

    Bit 4 (voltage enabled) is set in the states with the power stage
    supplied, bit 9 (remote) when the controlword is obeyed, bit 10 (target
    reached) on request; the don't-care state bits are 0 except bit 5 (quick
    stop, active low) which is 1 outside the quick stop and fault states.
    """
    word = SW_MASK[state][1]
    if state in (S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED):
        word |= 0x20
    if state in (S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE):
        word |= 0x10
    if remote:
        word |= 0x200
    if target_reached:
        word |= 0x400
    return word


def decode_controlword(controlword: int, previous: int = 0) -> int | None:
    """The device control command a controlword carries, as its canonical ``CW_*`` value.

    ``previous`` is the controlword received before, for the fault reset
    edge. Returns ``None`` while bit 7 is held high without a rising edge
    (the drive then ignores the other bits).
    """
    if controlword & CW_FAULT_RESET_BIT:
        return None if previous & CW_FAULT_RESET_BIT else CW_FAULT_RESET
    if not controlword & 0x02:
        return CW_DISABLE_VOLTAGE  # 0bx xx0x
    if not controlword & 0x04:
        return CW_QUICK_STOP  # 0bx x01x
    if not controlword & 0x01:
        return CW_SHUTDOWN  # 0bx x110
    return CW_ENABLE_OPERATION if controlword & 0x08 else CW_SWITCH_ON


def _drive_edges() -> dict[tuple[CiA402State, int], CiA402State]:
    edges = {(src, cw): dst for (src, dst), cw in TRANSITIONTABLE.items()}
    for (src, dst), cws in ALSO_TRIGGERED_BY.items():
        for cw in cws:
            edges[(src, cw)] = dst
    return edges


_DRIVE_EDGES = _drive_edges()


def next_state(current: CiA402State, controlword: int, previous: int = 0) -> CiA402State:
    """Drive side: the state after receiving ``controlword`` in ``current``.

    Commands that name no transition out of ``current`` leave it unchanged,
    as the standard says. "Switch on + enable operation" in READY TO SWITCH
    ON performs transitions 3 and 4 at once.
    """
    command = decode_controlword(controlword, previous)
    if command is None:
        return current
    state = _DRIVE_EDGES.get((current, command), current)
    if state is S.SWITCHED_ON and command == CW_ENABLE_OPERATION:
        state = _DRIVE_EDGES[(state, command)]
    return state


def interpolation_period(period_s: float) -> tuple[int, int]:
    """0x60C2 ``(value, index)`` with ``period_s = value * 10**index``, the coarsest exact one.

    Raises
    ------
    UsageError
        When no ``value`` in 1..255 with ``index`` in -6..0 gives ``period_s``
        to within 1 ns.
    """
    for index in range(0, -7, -1):
        value = round(period_s * 10**-index)
        if 1 <= value <= 255 and abs(value * 10.0**index - period_s) < 1e-9:
            return value, index
    raise UsageError(
        f"cycle period {period_s} s has no 0x60C2 form value * 10^index (value 1..255)"
    )


def plan(current: CiA402State, target: CiA402State) -> list[Step]:
    """Host side: the shortest list of steps from ``current`` to ``target``.

    Each :class:`Step` names the controlword to send (``None`` for an
    automatic transition to wait for) and the state to expect next.

    Raises
    ------
    StateTransitionError
        When no controlword sequence leads there (FAULT and the transient
        states are entered by the drive only).
    """
    if current is target:
        return []
    edges: dict[CiA402State, list[Step]] = {}
    for (src, dst), cw in TRANSITIONTABLE.items():
        edges.setdefault(src, []).append(Step(cw, dst))
    for src, dst in AUTOMATIC.items():
        edges.setdefault(src, []).append(Step(None, dst))
    previous: dict[CiA402State, tuple[CiA402State, Step]] = {}
    queue = deque([current])
    while queue:
        state = queue.popleft()
        for step in edges.get(state, []):
            if step.next_state in previous or step.next_state is current:
                continue
            previous[step.next_state] = (state, step)
            if step.next_state is target:
                path: list[Step] = []
                node = target
                while node is not current:
                    node, taken = previous[node]
                    path.append(taken)
                return path[::-1]
            queue.append(step.next_state)
    raise StateTransitionError(
        f"no CiA 402 controlword sequence leads from {current.value} to {target.value}"
    )
