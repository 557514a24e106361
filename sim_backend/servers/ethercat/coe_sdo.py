"""The CoE SDO server of the served slave (ETG.1000.6 5.6.2, CiA 301 7.2.4.3).

:class:`SdoServer` answers SDO requests from the mailbox on a canopen
:class:`~canopen.LocalNode` (whose read/write callbacks are the drive's object
logic, :mod:`servobench.sim_backend.servers.canopen.drive`). Command bytes::

    upload request        0x40 (0x50 complete access)
    upload response       expedited 0x43 | (4 - n) << 2; normal 0x41 + size (4) + data
    upload segment        request 0x60 | t; response t | n << 1 | last, 7+ data bytes
    download expedited    0x23 | (4 - n) << 2 (0x21/0x31: normal, complete access) + size
    download response     0x60;  download segment: request t | n << 1 | last, response 0x20 | t
    abort                 0x80 + index + subindex + CiA 301 abort code (4)

    t = toggle bit 0x10; n = bytes not used of the 7 (segments) or 4 (expedited).

A normal upload puts as much data as the mailbox holds into the initiate
response and the rest into segments, as EtherCAT masters expect (SOEM reads
``length - 10`` bytes there). Complete access (bit 4) reads or writes all
subindices the object defines (not only the sub 0 value many) from
subindex 0 (as 16 bits: 8 of value, 8 of padding) or 1, each in its own
size; a complete write stores sub 0 = 0, the entries, then the new sub 0
(for the objects in ``count_from_padding``, as a faulty drive does, the
padding byte after the count instead: ``--profile ca-stored-wrong``).
"""

from __future__ import annotations

import struct

import canopen
from canopen.objectdictionary import ODVariable
from canopen.sdo import SdoAbortedError

from servobench.sim_backend.servers.ethercat.mailbox import (
    COE_SDO_REQUEST,
    COE_SDO_RESPONSE,
    MBXERR_SERVICE_NOT_SUPPORTED,
    TYPE_COE,
    Mailbox,
    coe_header,
    coe_service,
    encode_mailbox,
    mailbox_error,
)

# CiA 301 SDO abort codes the server gives.
ABORT_TOGGLE = 0x05030000
ABORT_COMMAND = 0x05040001
ABORT_UNSUPPORTED_ACCESS = 0x06010000
ABORT_NO_OBJECT = 0x06020000
ABORT_LENGTH = 0x06070010
ABORT_LENGTH_HIGH = 0x06070012
ABORT_NO_SUBINDEX = 0x06090011
ABORT_GENERAL = 0x08000000

_TOGGLE = 0x10
_CA = 0x10
#: Mailbox header (6) + CoE header (2) + command, index, subindex (4) + size (4).
_INIT_OVERHEAD = 16
#: Mailbox header (6) + CoE header (2) + command (1).
_SEGMENT_OVERHEAD = 9


class SdoServer:
    """SDO over CoE for ``node``, with mailboxes of ``mailbox_bytes`` (the send SM's length)."""

    def __init__(
        self,
        node: canopen.LocalNode,
        mailbox_bytes: int,
        complete_access: bool = True,
        count_from_padding: frozenset[int] = frozenset(),
    ) -> None:
        self.node = node
        self.mailbox_bytes = mailbox_bytes
        self.complete_access = complete_access  #: False: complete access aborts 0x06010000
        #: Objects whose complete write stores sub 0 from the padding byte (a drive's bug).
        self.count_from_padding = count_from_padding
        self._upload: tuple[int, int, bytes, int] | None = None  # index, sub, rest, toggle
        self._download: tuple[int, int, bool, int, bytearray, int] | None = None
        self.counter = 0

    # ------------------------------------------------------------ objects
    def _subindices(self, index: int) -> list[int]:
        if index not in self.node.object_dictionary:
            raise SdoAbortedError(ABORT_NO_OBJECT)
        obj = self.node.object_dictionary[index]
        if isinstance(obj, ODVariable):
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)  # no complete access to a variable
        return sorted(s for s in obj.subindices if s > 0)  # every defined one, as SSC slaves

    def read(self, index: int, sub: int, complete: bool) -> bytes:
        """The bytes of ``index:sub`` (or all of it with ``complete``)."""
        if complete and not self.complete_access:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
        if not complete:
            return self.node.get_data(index, sub, check_readable=True)
        subs = self._subindices(index)
        data = b"".join(self.node.get_data(index, s, check_readable=True) for s in subs)
        return (self.node.get_data(index, 0) + b"\x00" + data) if sub == 0 else data

    def write(self, index: int, sub: int, complete: bool, data: bytes) -> None:
        """Write ``data`` to ``index:sub`` (or its subindices from ``sub`` with ``complete``)."""
        if complete and not self.complete_access:
            raise SdoAbortedError(ABORT_UNSUPPORTED_ACCESS)
        if not complete:
            self.node.set_data(index, sub, data, check_writable=True)
            return
        if index not in self.node.object_dictionary or isinstance(
            self.node.object_dictionary[index], ODVariable
        ):
            raise SdoAbortedError(ABORT_NO_OBJECT if index not in self.node.object_dictionary
                                  else ABORT_UNSUPPORTED_ACCESS)  # fmt: skip
        obj = self.node.object_dictionary[index]
        pos, count = 0, None
        if sub == 0:
            if len(data) < 2:
                raise SdoAbortedError(ABORT_LENGTH)
            count, pos = data[0], 2
            self.node.set_data(index, 0, b"\x00", check_writable=True)
        s = 1
        while pos < len(data) and (count is None or s <= count):
            if s not in obj:
                raise SdoAbortedError(ABORT_LENGTH_HIGH)
            size = len(obj[s]) // 8
            if pos + size > len(data):
                raise SdoAbortedError(ABORT_LENGTH)
            self.node.set_data(index, s, data[pos : pos + size], check_writable=True)
            pos, s = pos + size, s + 1
        if count is not None:
            stored = data[1:2] if index in self.count_from_padding else bytes([count])
            self.node.set_data(index, 0, stored, check_writable=True)

    # ----------------------------------------------------------- requests
    def handle(self, message: Mailbox) -> bytes | None:
        """The reply mailbox for a CoE message (``None``: nothing to answer)."""
        self.counter = message.counter
        if coe_service(message.data) != COE_SDO_REQUEST:
            return mailbox_error(MBXERR_SERVICE_NOT_SUPPORTED, message.counter)
        body = message.data[2:]
        if len(body) < 4:
            return None
        command = body[0]
        index, sub = struct.unpack_from("<HB", body, 1)
        try:
            return self._dispatch(command, index, sub, body)
        except SdoAbortedError as err:
            self._upload = self._download = None
            return self._abort(index, sub, err.code)
        except (KeyError, ValueError, struct.error):
            self._upload = self._download = None
            return self._abort(index, sub, ABORT_GENERAL)

    def _dispatch(self, command: int, index: int, sub: int, body: bytes) -> bytes:
        ccs = command >> 5
        if ccs == 2:  # initiate upload
            return self._initiate_upload(index, sub, bool(command & _CA))
        if ccs == 3:  # upload segment
            return self._upload_segment(command)
        if ccs == 1:  # initiate download
            return self._initiate_download(command, index, sub, body)
        if ccs == 0:  # download segment
            return self._download_segment(command, body)
        if ccs == 4:  # abort from the master
            self._upload = self._download = None
            return None
        raise SdoAbortedError(ABORT_COMMAND)

    def _reply(self, payload: bytes, service: int = COE_SDO_RESPONSE) -> bytes:
        return encode_mailbox(Mailbox(TYPE_COE, self.counter, coe_header(service) + payload))

    def _abort(self, index: int, sub: int, code: int) -> bytes:
        """An abort travels as an SDO *request* (ETG.1000.6 5.6.2.7), whoever sends it."""
        return self._reply(struct.pack("<BHBI", 0x80, index, sub, code), COE_SDO_REQUEST)

    def _initiate_upload(self, index: int, sub: int, complete: bool) -> bytes:
        self._upload = None
        data = self.read(index, sub, complete)
        ca = _CA if complete else 0
        if len(data) <= 4 and not complete:
            command = 0x43 | (4 - len(data)) << 2
            return self._reply(struct.pack("<BHB", command, index, sub) + data.ljust(4, b"\x00"))
        room = self.mailbox_bytes - _INIT_OVERHEAD
        head, rest = data[:room], data[room:]
        if rest:
            self._upload = (index, sub, rest, 0)
        return self._reply(struct.pack("<BHBI", 0x41 | ca, index, sub, len(data)) + head)

    def _upload_segment(self, command: int) -> bytes:
        if self._upload is None:
            raise SdoAbortedError(ABORT_COMMAND)
        index, sub, rest, toggle = self._upload
        if command & _TOGGLE != toggle:
            raise SdoAbortedError(ABORT_TOGGLE)
        room = self.mailbox_bytes - _SEGMENT_OVERHEAD
        chunk, rest = rest[:room], rest[room:]
        last = not rest
        self._upload = None if last else (index, sub, rest, toggle ^ _TOGGLE)
        unused = 7 - len(chunk) if len(chunk) < 7 else 0
        reply = bytes([toggle | unused << 1 | (1 if last else 0)]) + chunk.ljust(7, b"\x00")
        return self._reply(reply)

    def _initiate_download(self, command: int, index: int, sub: int, body: bytes) -> bytes:
        self._download = None
        complete = bool(command & _CA)
        if command & 0x02:  # expedited
            n = 4 - (command >> 2 & 0x03) if command & 0x01 else 4
            self.write(index, sub, complete, body[4 : 4 + n])
            return self._reply(struct.pack("<BHBI", 0x60, index, sub, 0))
        (size,) = struct.unpack_from("<I", body, 4)
        data = bytearray(body[8 : 8 + size])
        if len(data) >= size:
            self.write(index, sub, complete, bytes(data[:size]))
        else:
            self._download = (index, sub, complete, size, data, 0)
        return self._reply(struct.pack("<BHBI", 0x60, index, sub, 0))

    def _download_segment(self, command: int, body: bytes) -> bytes:
        if self._download is None:
            raise SdoAbortedError(ABORT_COMMAND)
        index, sub, complete, size, data, toggle = self._download
        if command & _TOGGLE != toggle:
            raise SdoAbortedError(ABORT_TOGGLE)
        segment = body[1:]
        if command & 0x01 and len(segment) == 7:
            segment = segment[: 7 - (command >> 1 & 0x07)]
        data += segment
        if command & 0x01:
            self._download = None
            if len(data) < size:
                raise SdoAbortedError(ABORT_LENGTH)
            self.write(index, sub, complete, bytes(data[:size]))
        else:
            self._download = (index, sub, complete, size, data, toggle ^ _TOGGLE)
        return self._reply(bytes([0x20 | toggle]) + bytes(7))
