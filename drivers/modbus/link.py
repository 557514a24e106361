"""The Modbus link of ``modbus+tcp://`` and ``modbus+rtu://`` drives: requests out, typed errors back.

:class:`ModbusLink` wraps one pymodbus client. Every request goes through
:meth:`ModbusLink.call`, which checks the result and turns every failure
into a typed error that says what happened:

* no answer: on RTU, "no answer from unit N at PORT" with what to check (the
  unit id, the line settings, the wiring), since a slave that is not there,
  or is addressed wrongly, stays silent (Modbus over Serial Line v1.02 §2.2);
  on TCP the same with the host;
* a gateway's exceptions 10 and 11 (the path to unit N is unavailable, or
  unit N behind it did not answer: often a wrong unit id);
* exceptions 1-3 (the request does not fit the drive: wrong function,
  address or value) and 4 (device failure: the drive's fault code is looked
  up) and 5/6 (busy).

A missing answer is never retried (the request may have been executed: a
repeated FC23 would apply a command twice, a repeated feedback read of a
lock-step drive would skip a sample), so it is a :class:`DriveTimeoutError`.
The one retry: exception 6 (server device busy) says the request was *not*
executed, so it is sent once more after :data:`BUSY_RETRY_S` (counted in
:attr:`ModbusLink.retries`); a second "busy" raises.
"""

from __future__ import annotations

import logging
import select
import time
from collections.abc import Callable
from typing import Any

from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.pdu import ModbusPDU

from servobench.errors import (
    DriveConfigError,
    DriveConnectionError,
    DriveError,
    DriveFaultError,
    DriveTimeoutError,
)

# The library's own log lines would reach stderr through logging's last-resort
# handler; every failure is raised as a typed error here instead. An application
# that configures logging still sees them.
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Pause before re-sending a request the drive answered "busy" (exception 6) [s].
BUSY_RETRY_S = 0.001
#: Modbus exception "illegal function": the drive lacks the function.
EXCEPTION_ILLEGAL_FUNCTION = 1
#: Modbus exception "server device failure".
EXCEPTION_DEVICE_FAILURE = 4
#: Modbus exception "server device busy": the request was not executed.
EXCEPTION_BUSY = 6

EXCEPTION_NAMES = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    7: "negative acknowledge",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


def exception_error(code: int, what: str, fault_code: int = 0, unit: int | None = None) -> DriveError:
    """The typed error for a Modbus exception response ``code`` to request ``what``.

    1-3 (the request does not fit the drive: wrong function, address or value)
    -> :class:`DriveConfigError`; 4 (device failure) -> :class:`DriveFaultError`
    carrying ``fault_code``; 5, 6, 11 (busy, no answer behind a gateway) ->
    :class:`DriveTimeoutError`; 10 -> :class:`DriveConnectionError`. For 10
    and 11 the message names ``unit`` and what to check.
    """
    text = f"{what}: Modbus exception {code} ({EXCEPTION_NAMES.get(code, 'unknown')})"
    who = f"unit {unit}" if unit is not None else "the unit"
    if code == EXCEPTION_ILLEGAL_FUNCTION:
        return DriveConfigError(
            f'{text}: the drive lacks this function (fc23 = false or "auto" in the map?)'
        )
    if code in (2, 3):
        return DriveConfigError(f"{text}: the register map does not fit this drive")
    if code == EXCEPTION_DEVICE_FAILURE:
        return DriveFaultError(f"{text}, fault register 0x{fault_code:04X}", fault_code)
    if code == 11:
        return DriveTimeoutError(
            f"{text}: a gateway answered that {who} behind it did not respond "
            "(no such unit id there, or the device is off or miswired)"
        )
    if code == 10:
        return DriveConnectionError(
            f"{text}: a gateway has no path to {who} (check the gateway's routing for this unit id)"
        )
    if code in (5, 6):
        return DriveTimeoutError(text)
    return DriveError(text)


class _RtuClient(ModbusSerialClient):
    """The pymodbus serial client, answering reads as soon as bytes arrive.

    The stock ``recv(None)`` polls ``in_waiting`` every millisecond until the
    line has been quiet for one poll, which adds 1-2 ms to every transaction.
    Here it blocks in ``select`` until bytes are there and returns them; the RTU
    framer accumulates partial frames until the CRC closes one.
    """

    def recv(self, size: int | None) -> bytes:
        if size is not None or self.socket is None:
            return super().recv(size)
        try:
            ready, _, _ = select.select(
                [self.socket.fileno()], [], [], self.comm_params.timeout_connect
            )
            if not ready:
                return b""
            return self.socket.read(max(1, self.socket.in_waiting))
        except OSError:
            self.close()
            raise ConnectionException(str(self)) from None


class ModbusLink:
    """One Modbus client and the translation of its failures (see the module doc).

    Parameters
    ----------
    unit : int
        Unit id (RTU slave address, TCP unit identifier).
    timeout_s : float
        Response timeout [s].
    rtu : (path, baud, parity) or None
        The serial line; ``None`` for TCP.
    tcp : (host, port) or None
        The server; ``None`` for RTU.
    """

    def __init__(
        self,
        unit: int,
        timeout_s: float,
        rtu: tuple[str, int, str] | None = None,
        tcp: tuple[str, int] | None = None,
    ) -> None:
        self.unit, self.timeout_s, self.rtu, self.tcp = unit, timeout_s, rtu, tcp
        self.where = rtu[0] if rtu else f"{tcp[0]}:{tcp[1]}"  # type: ignore[index]
        self.client: ModbusTcpClient | ModbusSerialClient | None = None
        #: Requests re-sent after a "busy" answer since the link was created.
        self.retries = 0
        #: Called to read the drive's fault code when a request gets exception 4.
        self.fault_lookup: Callable[[], int] | None = None

    def connect(self) -> None:
        if self.rtu:
            path, baud, parity = self.rtu
            client: ModbusTcpClient | ModbusSerialClient = _RtuClient(
                path, baudrate=baud, parity=parity, timeout=self.timeout_s, retries=0,
                reconnect_delay=0,
            )  # fmt: skip
        else:
            host, port = self.tcp  # type: ignore[misc]
            client = ModbusTcpClient(
                host, port=port, timeout=self.timeout_s, retries=0, reconnect_delay=0
            )
        if not client.connect():
            client.close()
            raise DriveConnectionError(f"cannot connect to Modbus unit {self.unit} at {self.where}")
        self.client = client

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
            self.client = None

    def silence_hint(self) -> str:
        """What to check when the drive does not answer at all."""
        if self.rtu:
            _, baud, parity = self.rtu
            return (
                f"no such unit on the line, or the line is set wrong (baud {baud}, parity "
                f"{parity}) or miswired: a slave addressed wrongly stays silent"
            )
        return "the server took the connection but does not answer for this unit id"

    def call(
        self,
        method: str,
        what: str,
        *,
        lookup_fault: bool = True,
        accept: frozenset[int] = frozenset(),
        **kwargs: Any,
    ) -> ModbusPDU:
        """Run the client's ``method`` for one request; translate every failure into a typed error.

        On exception 4 (device failure) the fault code is looked up
        (:attr:`fault_lookup`), unless ``lookup_fault`` is false. Exception
        responses whose code is in ``accept`` are returned, not raised.
        """
        response = self._request(method, what, **kwargs)
        if response is not None and getattr(response, "exception_code", 0) == EXCEPTION_BUSY:
            time.sleep(BUSY_RETRY_S)  # busy: not executed, so sending it again is safe
            self.retries += 1
            response = self._request(method, what, **kwargs)
        if response is None or response.isError():
            code = getattr(response, "exception_code", 0)
            if code in accept:
                return response
            fault = 0
            if code == EXCEPTION_DEVICE_FAILURE and lookup_fault and self.fault_lookup is not None:
                try:
                    fault = self.fault_lookup()
                except DriveError:
                    fault = 0
            raise exception_error(code, f"{what} at {self.where}", fault, self.unit)
        return response

    def _request(self, method: str, what: str, **kwargs: Any) -> ModbusPDU:
        """One request, link failures translated; the response is not checked here."""
        if self.client is None:
            raise DriveConnectionError(f"Modbus link to {self.where} is closed")
        try:
            return getattr(self.client, method)(device_id=self.unit, **kwargs)
        except ConnectionException as err:
            raise DriveConnectionError(f"{what}: link to {self.where} lost: {err}") from err
        except ModbusIOException as err:
            raise DriveTimeoutError(
                f"{what}: no answer from unit {self.unit} at {self.where} within "
                f"{self.timeout_s} s ({self.silence_hint()})"
            ) from err
        except ModbusException as err:
            raise DriveError(f"{what}: {err}") from err
