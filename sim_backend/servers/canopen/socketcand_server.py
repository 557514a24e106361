"""A virtual CAN bus served over TCP with the socketcand protocol.

:class:`SocketcandHub` is a small socketcand server of our own (raw mode
only, see :mod:`servobench.sim_backend.servers.canopen.wire` for the protocol) that acts as a CAN
bus: every frame one station sends reaches every *other* station, as on a
wire. Stations are TCP clients (python-can's ``socketcand`` interface, from
any process) and in-process :class:`LocalPort` s, which save the served drive
a TCP hop and a thread hand-off per frame.

It needs no CAN hardware and no kernel module, so a served simulated drive
and the host driver can run in separate processes on any machine, and a
second ``serve-sim`` can join the same hub as a TCP client to put another
node on the bus.

A TCP client gets every frame sent after its ``< rawmode >`` is acknowledged.
python-can reads that ``< ok >`` with one ``recv`` and fails if a frame
shares it, so the frames of a client's first :data:`JOIN_GRACE_S` are held
for it and delivered, in order, when the grace ends or as soon as the
client sends (it has then read the ``< ok >``). Error replies have
socketcand's form, ``< error TEXT >`` with no bracket inside the text
(``< error unknown command >`` as socketcand answers an unknown command).

Threading: one selector thread accepts clients and reads their commands;
frames are forwarded from the thread that received or sent them, local
ports are called synchronously in that thread. Each TCP client has its own
send lock, so stations may send from any thread.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
import time
from collections.abc import Callable, Sequence

from servobench.errors import DriveConnectionError
from servobench.sim_backend.servers.canopen.wire import (
    CanFrame,
    WireError,
    command_words,
    encode_frame,
    parse_send,
    split_commands,
)

#: Bus name served (the ``< open NAME >`` a client must ask for).
DEFAULT_CHANNEL = "vcan0"
#: Frames for a client that has not sent yet are held this long after its ``< rawmode >`` is
#: acknowledged, then delivered [s]: python-can reads the ``< ok >`` reply with one ``recv``
#: and fails if a frame shares it.
JOIN_GRACE_S = 0.1
#: A client that does not take a frame within this time is dropped [s].
SEND_TIMEOUT_S = 2.0
#: Selector wake-up period, to notice :meth:`SocketcandHub.close` [s].
POLL_S = 0.2
#: Largest unterminated command kept from a client [characters].
MAX_PENDING_CHARS = 4096


class LocalPort:
    """An in-process station on a :class:`SocketcandHub`.

    ``receive(frame)`` is called for every frame another station sends, in
    the sender's thread; :meth:`send` puts a frame on the bus.
    """

    def __init__(self, hub: SocketcandHub, receive: Callable[[CanFrame], None]) -> None:
        self._hub = hub
        self.receive = receive

    def send(self, *frames: CanFrame) -> None:
        """Put ``frames`` on the bus, back to back."""
        self._hub.broadcast(frames, source=self)

    def close(self) -> None:
        self._hub.detach(self)


def error_reply(text: str) -> str:
    """``< error TEXT >``, socketcand's error form: no bracket inside, one command."""
    return f"< error {text.replace('<', '').replace('>', '').strip()} >"


class _Client:
    """One TCP station and where it is in the socketcand handshake."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.pending = ""
        self.state = "hello"  # -> "open" after < open >, -> "raw" after < rawmode >
        self.raw_since = 0.0
        self.has_sent = False
        self.closed = False
        self.send_lock = threading.Lock()
        self.held: list[str] = []  #: frames sent during the join grace, in order

    def grace_ends(self) -> float | None:
        """When the held frames go out (``time.monotonic()``), ``None`` if none are held."""
        return self.raw_since + JOIN_GRACE_S if self.held else None

    def send_text(self, text: str) -> None:
        with self.send_lock:
            self.sock.sendall(text.encode("ascii"))

    def acknowledge_raw(self) -> None:
        """Answer ``< rawmode >``: from here on every frame is this client's."""
        with self.send_lock:
            self.sock.sendall(b"< ok >")
            self.state = "raw"
            self.raw_since = time.monotonic()

    def deliver(self, text: str) -> None:
        """Frames for this client: sent, or held while its join grace lasts."""
        with self.send_lock:
            if self.state != "raw":
                return  # not subscribed yet
            if not self.has_sent and time.monotonic() - self.raw_since < JOIN_GRACE_S:
                if text:
                    self.held.append(text)
                return
            text, self.held = "".join(self.held) + text, []
            if text:
                self.sock.sendall(text.encode("ascii"))

    def note_sent(self) -> None:
        """The client sent a frame, so it has read the ``< ok >``: nothing is held any longer."""
        with self.send_lock:
            self.has_sent = True
        self.deliver("")

    def drop(self) -> None:
        """Mark closed and wake the selector (EOF), from any thread."""
        self.closed = True
        with contextlib.suppress(OSError):  # already disconnected
            self.sock.shutdown(socket.SHUT_RDWR)


class SocketcandHub:
    """A socketcand server that is a virtual CAN bus hub.

    Parameters
    ----------
    host : str
        Listen address.
    port : int
        TCP port; 0 picks a free one (see :attr:`address`).
    channel : str
        Bus name clients open.

    Examples
    --------
    >>> with SocketcandHub() as hub:                              # doctest: +SKIP
    ...     bus = can.Bus(interface="socketcand", channel="vcan0",
    ...                   host=hub.address[0], port=hub.address[1])
    """

    def __init__(
        self, host: str = "127.0.0.1", port: int = 0, channel: str = DEFAULT_CHANNEL
    ) -> None:
        self.host = host
        self.port = port
        self.channel = channel
        self.failure: BaseException | None = None
        self._lock = threading.Lock()
        self._clients: list[_Client] = []
        self._ports: list[LocalPort] = []
        self._listener: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()

    @property
    def address(self) -> tuple[str, int]:
        """``(host, port)`` the hub listens on."""
        if self._listener is None:
            raise DriveConnectionError("socketcand hub is not started")
        host, port = self._listener.getsockname()[:2]
        return host, port

    def start(self) -> SocketcandHub:
        try:
            listener = socket.create_server((self.host, self.port), backlog=16)
        except OSError as err:
            raise DriveConnectionError(
                f"cannot listen for socketcand on {self.host}:{self.port}: {err}"
            ) from err
        self._listener = listener
        self._thread = threading.Thread(target=self._run, name="socketcand-hub", daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        """Disconnect every client and stop. Safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2 * POLL_S + 1.0)
            self._thread = None

    def __enter__(self) -> SocketcandHub:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --------------------------------------------------------------- stations
    def attach(self, receive: Callable[[CanFrame], None]) -> LocalPort:
        """Add an in-process station; ``receive`` gets every frame others send."""
        port = LocalPort(self, receive)
        with self._lock:
            self._ports.append(port)
        return port

    def detach(self, port: LocalPort) -> None:
        with self._lock:
            if port in self._ports:
                self._ports.remove(port)

    @property
    def client_count(self) -> int:
        """TCP stations connected now."""
        with self._lock:
            return sum(not c.closed for c in self._clients)

    def broadcast(self, frames: Sequence[CanFrame], source: object = None) -> None:
        """Deliver ``frames``, in order, to every station except ``source``.

        Each TCP client gets them in one write (one segment, one wake-up).
        """
        if not frames:
            return
        now = time.time()
        text = "".join(encode_frame(frame, now) for frame in frames)
        with self._lock:
            clients = list(self._clients)
            ports = list(self._ports)
        for client in clients:
            if client is source or client.closed:
                continue
            try:
                client.deliver(text)
            except OSError:
                client.drop()
        for port in ports:
            if port is not source:
                for frame in frames:
                    port.receive(frame)

    # ------------------------------------------------------------ the thread
    def _run(self) -> None:
        assert self._listener is not None
        sel = selectors.DefaultSelector()
        self._listener.setblocking(False)
        sel.register(self._listener, selectors.EVENT_READ, None)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=self._wake_in()):
                    if key.data is None:
                        self._accept(sel)
                    else:
                        self._serve(sel, key.data)
                self._release_held()
        except BaseException as err:  # a station's receive() failed: stop the bus loudly
            self.failure = err
            raise
        finally:
            with self._lock:
                clients, self._clients = self._clients, []
            for client in clients:
                client.drop()
                client.sock.close()
            sel.close()
            self._listener.close()

    def _wake_in(self) -> float:
        """Selector time-out [s]: :data:`POLL_S`, or sooner when a join grace ends."""
        with self._lock:
            ends = [t for c in self._clients if (t := c.grace_ends()) is not None]
        return max(0.0, min([POLL_S, *(t - time.monotonic() for t in ends)]))

    def _release_held(self) -> None:
        """Deliver the held frames of clients whose join grace has ended."""
        with self._lock:
            due = [c for c in self._clients if c.held and not c.closed]
        for client in due:
            try:
                client.deliver("")
            except OSError:
                client.drop()

    def _accept(self, sel: selectors.BaseSelector) -> None:
        try:
            sock, _ = self._listener.accept()  # type: ignore[union-attr]
        except BlockingIOError:
            return
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        sock.settimeout(SEND_TIMEOUT_S)
        client = _Client(sock)
        with self._lock:
            self._clients.append(client)
        sel.register(sock, selectors.EVENT_READ, client)
        try:
            client.send_text("< hi >")
        except OSError:
            client.drop()

    def _remove(self, sel: selectors.BaseSelector, client: _Client) -> None:
        client.closed = True
        sel.unregister(client.sock)
        client.sock.close()
        with self._lock:
            self._clients.remove(client)

    def _serve(self, sel: selectors.BaseSelector, client: _Client) -> None:
        try:
            data = client.sock.recv(65536)
        except OSError:
            data = b""
        if not data or client.closed:
            self._remove(sel, client)
            return
        commands, client.pending = split_commands(client.pending + data.decode("ascii", "replace"))
        if len(client.pending) > MAX_PENDING_CHARS:
            client.pending = ""
        frames: list[CanFrame] = []
        try:
            for command in commands:
                frame = self._handle(client, command)
                if frame is not None:
                    frames.append(frame)
            self.broadcast(frames, source=client)
        except OSError:
            client.drop()

    def _handle(self, client: _Client, command: str) -> CanFrame | None:
        """Answer one command; return the frame of a ``< send >`` for the caller to forward."""
        words = command_words(command)
        verb = words[0] if words else ""
        if verb == "send" and client.state in ("open", "raw"):
            try:
                frame = parse_send(command)
            except WireError as err:
                client.send_text(error_reply(str(err)))
                return None
            if not client.has_sent:
                client.note_sent()
            return frame
        if verb == "open" and client.state == "hello":
            if words[1:] == [self.channel]:
                client.state = "open"
                client.send_text("< ok >")
            else:
                client.send_text(error_reply(f"could not open bus {' '.join(words[1:])}"))
        elif verb == "rawmode" and client.state in ("open", "raw"):
            client.acknowledge_raw()
        elif verb == "echo":
            client.send_text("< echo >")
        else:
            client.send_text(error_reply("unknown command"))
        return None
