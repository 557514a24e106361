"""The EtherCAT AL (application layer) state machine as data (ETG.1000.6 section 6.4).

Pure: no I/O. The master writes the requested state into AL control
(0x0120, bit 4 = error acknowledge); the slave answers in AL status
(0x0130, bit 4 = error indication) and AL status code (0x0134)::

            +-------+   (IP)    +--------+   (PS)    +---------+  (SO)  +----+
            | INIT  | --------> | PRE-OP | --------> | SAFE-OP | -----> | OP |
            |  0x01 | <-------- |  0x02  | <-------- |  0x04   | <----- |0x08|
            +-------+  (PI)     +--------+   (SP)    +---------+  (OS)  +----+
               ^ | (IB)   (SI, OI from SAFE-OP and OP; OP, SAFE-OP -> PRE-OP: OP, SP)
               | v
            +-------+
            | BOOT  | 0x03  (entered from and left to INIT only)
            +-------+

A request that names no transition out of the present state fails with
0x0011 (invalid requested state change), one that names no state at all
with 0x0012 (unknown requested state); the slave then sets the error flag
and stays. While the flag is set only a request with the acknowledge bit
(or one to a lower state) is processed.
"""

from __future__ import annotations

from enum import IntEnum
from typing import NamedTuple


class AlState(IntEnum):
    INIT = 0x01
    PRE_OP = 0x02
    BOOT = 0x03
    SAFE_OP = 0x04
    OP = 0x08


#: AL status / control bit 4: error indication (status), error acknowledge (control).
ERROR_FLAG = 0x10
STATE_MASK = 0x0F

# AL status codes (ETG.1000.6 table 11) the served slave reports.
NO_ERROR = 0x0000
#: Not a status code: the application completes the transition later (SAFE-OP -> OP
#: waits for valid outputs); the slave stays where it is, without error, meanwhile.
PENDING = -1
UNSPECIFIED = 0x0001
INVALID_STATE_CHANGE = 0x0011
UNKNOWN_STATE = 0x0012
BOOT_NOT_SUPPORTED = 0x0013
INVALID_MAILBOX_CONFIG = 0x0016
SM_WATCHDOG = 0x001B
INVALID_OUTPUT_CONFIG = 0x001D
INVALID_INPUT_CONFIG = 0x001E
INVALID_DC_SYNC_CONFIG = 0x0030

STATUS_CODE_TEXT = {
    NO_ERROR: "no error",
    UNSPECIFIED: "unspecified error",
    INVALID_STATE_CHANGE: "invalid requested state change",
    UNKNOWN_STATE: "unknown requested state",
    BOOT_NOT_SUPPORTED: "bootstrap not supported",
    INVALID_MAILBOX_CONFIG: "invalid mailbox configuration",
    SM_WATCHDOG: "sync manager watchdog",
    INVALID_OUTPUT_CONFIG: "invalid output configuration",
    INVALID_INPUT_CONFIG: "invalid input configuration",
    INVALID_DC_SYNC_CONFIG: "invalid DC SYNC configuration",
}

A = AlState
#: ``from -> states it may go to`` (the arrows of the diagram).
TRANSITIONS: dict[AlState, frozenset[AlState]] = {
    A.INIT: frozenset({A.PRE_OP, A.BOOT}),  # IP, IB
    A.PRE_OP: frozenset({A.INIT, A.SAFE_OP}),  # PI, PS
    A.SAFE_OP: frozenset({A.INIT, A.PRE_OP, A.OP}),  # SI, SP, SO
    A.OP: frozenset({A.INIT, A.PRE_OP, A.SAFE_OP}),  # OI, OP, OS
    A.BOOT: frozenset({A.INIT}),  # BI
}


class Request(NamedTuple):
    """What an AL control write asks: ``target`` (``None`` when no state), the ack bit."""

    target: AlState | None
    acknowledge: bool


def decode_control(value: int) -> Request:
    """AL control (0x0120) as a request."""
    try:
        target = AlState(value & STATE_MASK)
    except ValueError:
        target = None
    return Request(target, bool(value & ERROR_FLAG))


def check_request(current: AlState, request: Request) -> int:
    """The AL status code a request earns in ``current``: 0 when the transition is allowed.

    A request for the present state is allowed (nothing to do).
    """
    if request.target is None:
        return UNKNOWN_STATE
    if request.target is current or request.target in TRANSITIONS[current]:
        return NO_ERROR
    return INVALID_STATE_CHANGE


def ignored_while_in_error(current: AlState, request: Request) -> bool:
    """True when the error flag is set and the request neither acknowledges nor goes down."""
    if request.acknowledge or request.target is None:
        return False
    return request.target >= current if request.target is not A.BOOT else True


def encode_status(state: AlState, error: bool) -> int:
    """AL status (0x0130)."""
    return int(state) | (ERROR_FLAG if error else 0)
