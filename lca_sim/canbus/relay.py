"""The CAN relay behind `lca-can-server`: every frame a client sends goes to every other client.

One thread, non-blocking sockets. It copies every frame a client sends to every other client
(and back to the sender when it asked for `receive_own_messages`), as a bus does, relaying the
websocket payload without decoding it into a `can.Message`. It binds 127.0.0.1 unless told
otherwise. A client that reads too slowly for its backlog (`max_backlog_bytes`) is disconnected
rather than allowed to stall the others. A stock python-can-remote client (`interface="remote"`)
can join for send and receive; its server-side periodic sends are refused (logged). Why this and
not python-can-remote's own server: docs/can-transport.md.
"""

from __future__ import annotations

import json
import logging
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

from lca_sim.canbus.remote import INTERFACE_NAME
from lca_sim.canbus.wire import (
    DEFAULT_HOST,
    DEFAULT_PORT,
    HEADER,
    MAX_HTTP_REQUEST,
    MESSAGE_TYPE,
    OP_BINARY,
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    PROTOCOL,
    RECV_CHUNK,
    ProtocolError,
    accept_key,
    parse_frames,
    ws_frame,
)
from lca_sim.runtime import FreezeWatch

logger = logging.getLogger(__name__)

# The longest the relay waits in one `select`: a return later than this (plus the freeze
# threshold) after the one before means the relay stood still, and every frame waited with it.
POLL_S = 0.05
# A stall of the relay longer than this is logged as a warning: the shipped drives' RPDO
# deadline (100 ms) is the tightest a stall of the bus can trip.
STALL_WARN_S = 0.1


@dataclass
class RelayStats:
    """What the relay did since it started."""

    connections: int = 0
    frames_in: int = 0
    frames_out: int = 0
    bad_messages: int = 0
    dropped_clients: int = 0
    freezes: int = 0  # stalls of the relay's own process (`POLL_S`)
    longest_freeze_s: float = 0.0


@dataclass(eq=False)
class _Client:
    sock: socket.socket
    peer: str
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    upgraded: bool = False
    member: bool = False  # sent its bus_request: receives the bus's frames
    receive_own: bool = False
    closing: bool = False
    writing: bool = False


class RelayServer:
    """Relay CAN frames between websocket clients, as one bus; one thread, `serve()`."""

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        max_backlog_bytes: int = 1 << 20,
    ) -> None:
        """Bind and listen (port 0: any free port, see `port`); nothing is served yet."""
        self._listener = socket.create_server((host, port), backlog=16)
        self._listener.setblocking(False)
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ, None)
        self._clients: dict[int, _Client] = {}
        self._members: list[_Client] = []
        self._max_backlog = max_backlog_bytes
        self._stop = threading.Event()
        self.stats = RelayStats()
        self._freezes = FreezeWatch()
        self.host = host
        self.port: int = self._listener.getsockname()[1]

    @property
    def url(self) -> str:
        """The channel clients give: ws://host:port/."""
        return f"ws://{self.host}:{self.port}/"

    def stop(self) -> None:
        """Make `serve()` return (from any thread or a signal handler)."""
        self._stop.set()

    def serve(self, poll_s: float = POLL_S) -> None:
        """Relay until `stop()`; then close every connection and the listener.

        A stall of the relay's process (the host paused it, or it was not scheduled) holds
        every frame on the bus as long: a drive's heartbeat consumer or RPDO deadline may
        then fire though no node was silent. Such a stall is told by two `select` returns
        further apart than `poll_s` plus `FREEZE_THRESHOLD_S`; it is counted in `stats` and
        logged (`FreezeWatch.note`: the first, and the first beyond `STALL_WARN_S`).
        """
        last_return = time.monotonic()
        try:
            while not self._stop.is_set():
                ready = self._selector.select(poll_s)
                now = time.monotonic()
                self._watch_freeze(now - last_return - poll_s)
                last_return = now
                for key, events in ready:
                    if key.data is None:
                        self._accept()
                        continue
                    client: _Client = key.data
                    if events & selectors.EVENT_READ:
                        self._read(client)
                    if events & selectors.EVENT_WRITE and not client.closing:
                        self._flush(client)
                for client in list(self._clients.values()):
                    if client.outbuf and not client.writing:
                        self._flush(client)
                    elif client.closing and not client.outbuf:
                        self._drop(client)
        finally:
            for client in list(self._clients.values()):
                self._drop(client)
            self._selector.close()
            self._listener.close()

    def _watch_freeze(self, late_s: float) -> None:
        freeze = self._freezes.check(late_s)
        if freeze is None:
            return
        self.stats.freezes = self._freezes.count
        self.stats.longest_freeze_s = self._freezes.longest_s
        note = self._freezes.note(freeze, STALL_WARN_S, "every frame on the bus waited as long")
        if note is not None:
            logger.log(note[0], "relay: %s", note[1])

    # -- connections --

    def _accept(self) -> None:
        try:
            sock, address = self._listener.accept()
        except BlockingIOError:
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = _Client(sock, f"{address[0]}:{address[1]}")
        self._clients[sock.fileno()] = client
        self._selector.register(sock, selectors.EVENT_READ, client)
        self.stats.connections += 1
        logger.info("connection from %s", client.peer)

    def _drop(self, client: _Client, why: str = "") -> None:
        if self._clients.pop(client.sock.fileno(), None) is None:
            return
        if client in self._members:
            self._members.remove(client)
        self._selector.unregister(client.sock)
        client.sock.close()
        logger.info("%s left%s", client.peer, f": {why}" if why else "")

    def _read(self, client: _Client) -> None:
        try:
            chunk = client.sock.recv(RECV_CHUNK)
        except BlockingIOError:
            return
        except OSError as exc:
            self._drop(client, str(exc))
            return
        if not chunk:
            self._drop(client)
            return
        client.inbuf += chunk
        if not client.upgraded:
            self._handshake(client)
            return
        try:
            frames = parse_frames(client.inbuf, limit=MAX_HTTP_REQUEST)
        except ProtocolError as exc:
            self._drop(client, str(exc))
            return
        self._dispatch(client, frames)

    def _dispatch(self, client: _Client, frames: list[tuple[int, bytes]]) -> None:
        for opcode, payload in frames:
            if opcode == OP_BINARY:
                self._relay(client, payload)
            elif opcode == OP_TEXT:
                self._event(client, payload)
            elif opcode == OP_PING:
                self._queue(client, ws_frame(OP_PONG, payload))
            elif opcode == OP_CLOSE:
                self._queue(client, ws_frame(OP_CLOSE, payload[:2]))
                client.closing = True
                if client in self._members:
                    self._members.remove(client)
                return

    def _handshake(self, client: _Client) -> None:
        end = client.inbuf.find(b"\r\n\r\n")
        if end < 0:
            if len(client.inbuf) > MAX_HTTP_REQUEST:
                self._drop(client, "HTTP request too long")
            return
        head = bytes(client.inbuf[:end]).decode("latin-1").split("\r\n")
        del client.inbuf[: end + 4]
        headers = {
            name.strip().lower(): value.strip()
            for name, sep, value in (line.partition(":") for line in head[1:])
            if sep
        }
        protocols = [p.strip() for p in headers.get("sec-websocket-protocol", "").split(",")]
        if headers.get("upgrade", "").lower() != "websocket" or "sec-websocket-key" not in headers:
            body = (
                f"lca-can-server: a CAN relay. python-can: interface={INTERFACE_NAME!r}, "
                f"channel='ws://<host>:<port>/'.\n{self.stats}\n{len(self._members)} clients\n"
            ).encode()
            self._respond(client, "200 OK", body)
            return
        if PROTOCOL not in protocols:
            self._respond(client, "400 Bad Request", f"subprotocol {PROTOCOL} only\n".encode())
            return
        response = (
            "HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Accept: {accept_key(headers['sec-websocket-key'])}\r\n"
            f"Sec-WebSocket-Protocol: {PROTOCOL}\r\n\r\n"
        )
        client.upgraded = True
        self._queue(client, response.encode("latin-1"))

    def _respond(self, client: _Client, status: str, body: bytes) -> None:
        head = (
            f"HTTP/1.1 {status}\r\nContent-Type: text/plain; charset=utf-8\r\n"
            f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
        )
        self._queue(client, head.encode("latin-1") + body)
        client.closing = True

    def _event(self, client: _Client, payload: bytes) -> None:
        try:
            event = json.loads(payload)
            kind = event["type"]
        except (ValueError, KeyError, TypeError):
            self.stats.bad_messages += 1
            return
        if kind == "bus_request":
            config = event.get("payload", {}).get("config", {})
            client.receive_own = bool(config.get("receive_own_messages", False))
            response = {"type": "bus_response", "payload": {"channel_info": f"relay {self.url}"}}
            self._queue(client, ws_frame(OP_TEXT, json.dumps(response).encode()))
            if not client.member:
                client.member = True
                self._members.append(client)
        elif kind in ("periodic_start", "periodic_stop"):
            logger.warning(
                "%s asked for a server-side periodic send (python-can-remote's `remote` "
                "interface): not supported here, use interface %r",
                client.peer,
                INTERFACE_NAME,
            )
        else:
            self.stats.bad_messages += 1

    def _relay(self, sender: _Client, payload: bytes) -> None:
        if not sender.member or len(payload) < HEADER.size or payload[0] != MESSAGE_TYPE:
            self.stats.bad_messages += 1
            return
        self.stats.frames_in += 1
        frame = ws_frame(OP_BINARY, payload)
        for member in self._members:
            if member is not sender or sender.receive_own:
                self._queue(member, frame)
                self.stats.frames_out += 1

    def _queue(self, client: _Client, data: bytes) -> None:
        if client.closing:
            return
        client.outbuf += data
        if len(client.outbuf) > self._max_backlog:
            self.stats.dropped_clients += 1
            client.outbuf.clear()
            client.closing = True
            if client in self._members:
                self._members.remove(client)
            logger.warning("%s reads too slowly: disconnected", client.peer)

    def _flush(self, client: _Client) -> None:
        try:
            sent = client.sock.send(client.outbuf)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            self._drop(client, str(exc))
            return
        del client.outbuf[:sent]
        want_write = bool(client.outbuf)
        if want_write != client.writing:
            client.writing = want_write
            events = selectors.EVENT_READ | (selectors.EVENT_WRITE if want_write else 0)
            self._selector.modify(client.sock, events, client)
