"""CAN between processes (and machines) without kernel SocketCAN: a relay and its python-can bus.

The wire protocol is python-can-remote's (`can_remote`, a python-can interface over a websocket,
subprotocol "can.binary+json.v1"): an HTTP upgrade, a JSON `bus_request` answered by a JSON
`bus_response`, then one binary websocket message per CAN frame::

    01 | timestamp f64 | arbitration id u32 | dlc u8 | flags u8 | data      (big-endian)

with the flags extended id 0x01, remote frame 0x02, error frame 0x04, FD 0x08, bitrate switch
0x10, error state indicator 0x20. So 11- and 29-bit ids, RTR, CAN FD (up to 64 bytes), error
frames and 0-byte frames all cross unchanged; the timestamp is the sender's and is replaced by
the receive time (python-can's convention: `Message.timestamp` is when the frame arrived).

Two parts, both here (docs/can-transport.md says why this and not python-can-remote's own):

* `RemoteTransportBus`, the python-can interface `lca_remote` (setup.py registers it under the
  `can.interface` entry points): `can.Bus(interface="lca_remote",
  channel="ws://127.0.0.1:54701/")`. It opens the connection with python-can-remote's own
  handshake and then reads and writes the socket itself, buffered. Periodic sends are python-
  can's software ones (`BusABC.send_periodic`, a thread in this process), which python-can-
  remote 0.3.0's client gets wrong: its `modify_data` raises, so canopen's heartbeat stopped at
  the first NMT state change. Filters are applied by `BusABC.recv` as on every interface.
* `RelayServer`, the console script `lca-can-server`: one thread, non-blocking sockets, that
  copies every frame a client sends to every other client (and back to the sender when it
  asked for `receive_own_messages`), as a bus does. It relays the websocket payload without
  decoding it into a `can.Message` (python-can-remote's server opens a python-can virtual bus
  per client and runs two threads each, which capped it near 5,800 frames/s with three
  clients). It binds 127.0.0.1 unless told otherwise. A client that reads too slowly for its
  backlog (`max_backlog_bytes`) is disconnected rather than allowed to stall the others.

Compatibility: a stock python-can-remote client (`interface="remote"`) can join this relay for
send and receive; its server-side periodic sends are refused (logged). `lca_remote` can talk
to a stock `python -m can_remote` server too, e.g. one in front of a real can0 on another
machine.

    lca-can-server --port 54701                                  # terminal 1
    lca-virtual-drive --interface lca_remote --channel ws://127.0.0.1:54701/   # terminal 2
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import hashlib
import json
import logging
import random
import select
import selectors
import signal
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from types import FrameType
from typing import Any
from urllib.parse import urlsplit

import can
from can_remote.client import RemoteClientProtocol  # type: ignore[import-untyped]
from can_remote.websocket import WebSocket  # type: ignore[import-untyped]

from lca_sim.errors import EXIT_BAD_INPUT, EXIT_OK

logger = logging.getLogger(__name__)

INTERFACE_NAME = "lca_remote"
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 54701  # python-can-remote's default port
PROTOCOL = "can.binary+json.v1"  # python-can-remote's binary subprotocol (the only one relayed)
MESSAGE_TYPE = 0x01
HEADER = struct.Struct(">BdIBB")  # type, timestamp, arbitration id, dlc, flags
IS_EXTENDED_ID = 0x01
IS_REMOTE_FRAME = 0x02
IS_ERROR_FRAME = 0x04
IS_FD = 0x08
IS_BRS = 0x10
IS_ESI = 0x20
MAX_PAYLOAD = HEADER.size + 64  # the longest CAN FD frame
MAX_HTTP_REQUEST = 16384
CONNECT_TIMEOUT_S = 5.0
_WS_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_OP_TEXT, _OP_BINARY, _OP_CLOSE, _OP_PING, _OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA
_RECV_CHUNK = 65536


# --- the frame codec (python-can-remote's binary message) -------------------------------------


def encode_message(msg: can.Message) -> bytes:
    """One CAN frame as python-can-remote's binary websocket payload."""
    flags = (
        (IS_EXTENDED_ID if msg.is_extended_id else 0)
        | (IS_REMOTE_FRAME if msg.is_remote_frame else 0)
        | (IS_ERROR_FRAME if msg.is_error_frame else 0)
        | (IS_FD if msg.is_fd else 0)
        | (IS_BRS if msg.bitrate_switch else 0)
        | (IS_ESI if msg.error_state_indicator else 0)
    )
    header = HEADER.pack(MESSAGE_TYPE, msg.timestamp, msg.arbitration_id, msg.dlc, flags)
    return header + bytes(msg.data)


def decode_message(payload: bytes | bytearray, timestamp: float) -> can.Message:
    """A binary payload back into a frame, stamped `timestamp`; ValueError if it is not one."""
    if len(payload) < HEADER.size or payload[0] != MESSAGE_TYPE:
        raise ValueError(f"not a CAN frame message ({len(payload)} bytes)")
    _type, _sent, arbitration_id, dlc, flags = HEADER.unpack_from(payload)
    return can.Message(
        timestamp=timestamp,
        arbitration_id=arbitration_id,
        is_extended_id=bool(flags & IS_EXTENDED_ID),
        is_remote_frame=bool(flags & IS_REMOTE_FRAME),
        is_error_frame=bool(flags & IS_ERROR_FRAME),
        is_fd=bool(flags & IS_FD),
        bitrate_switch=bool(flags & IS_BRS),
        error_state_indicator=bool(flags & IS_ESI),
        dlc=dlc,
        data=bytes(payload[HEADER.size :]),
    )


# --- websocket framing (RFC 6455, the little of it this needs) --------------------------------


class ProtocolError(ValueError):
    """The peer broke the websocket framing."""


def _xor_mask(data: bytes, key: bytes) -> bytes:
    n = len(data)
    pad = (key * (n // 4 + 1))[:n]
    return (int.from_bytes(data, "little") ^ int.from_bytes(pad, "little")).to_bytes(n, "little")


def ws_frame(opcode: int, payload: bytes, mask: bool = False) -> bytes:
    """One final websocket frame; masked (as a client must send) with a random key if `mask`."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | n))
    elif n < 65536:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 126)) + struct.pack(">H", n)
    else:
        head = bytes((0x80 | opcode, (0x80 if mask else 0) | 127)) + struct.pack(">Q", n)
    if not mask:
        return head + payload
    key = random.getrandbits(32).to_bytes(4, "little")
    return head + key + _xor_mask(payload, key)


def parse_frames(buf: bytearray, limit: int = 65536) -> list[tuple[int, bytes]]:
    """Take every complete frame off the front of `buf`: (opcode, unmasked payload) each."""
    frames: list[tuple[int, bytes]] = []
    pos = 0
    size = len(buf)
    while size - pos >= 2:
        b1, b2 = buf[pos], buf[pos + 1]
        if not b1 & 0x80:
            raise ProtocolError("fragmented websocket messages are not supported")
        n = b2 & 0x7F
        head = 2
        if n == 126:
            if size - pos < 4:
                break
            (n,) = struct.unpack_from(">H", buf, pos + 2)
            head = 4
        elif n == 127:
            if size - pos < 10:
                break
            (n,) = struct.unpack_from(">Q", buf, pos + 2)
            head = 10
        if n > limit:
            raise ProtocolError(f"websocket frame of {n} bytes")
        masked = b2 & 0x80
        end = pos + head + (4 if masked else 0) + n
        if end > size:
            break
        if masked:
            key = bytes(buf[pos + head : pos + head + 4])
            payload = _xor_mask(bytes(buf[end - n : end]), key)
        else:
            payload = bytes(buf[end - n : end])
        frames.append((b1 & 0x0F, payload))
        pos = end
    del buf[:pos]
    return frames


def accept_key(key: str) -> str:
    """Sec-WebSocket-Accept for a Sec-WebSocket-Key."""
    return base64.b64encode(hashlib.sha1(key.encode("ascii") + _WS_GUID).digest()).decode()


def channel_url(channel: object) -> tuple[str, int, str]:
    """host, port, url of a channel: "ws://host:port/", "host:port" or "host" (default port)."""
    text = str(channel) if channel is not None else f"{DEFAULT_HOST}:{DEFAULT_PORT}"
    if "://" not in text:
        text = "ws://" + text
    parts = urlsplit(text)
    if parts.scheme != "ws":
        raise ValueError(f"channel {channel!r}: only ws:// is supported")
    host = parts.hostname or DEFAULT_HOST
    port = parts.port or DEFAULT_PORT
    return host, port, f"ws://{host}:{port}{parts.path or '/'}"


# --- the client: the python-can interface `lca_remote` ----------------------------------------


class RemoteTransportBus(can.BusABC):
    """A python-can bus on a relay (`lca-can-server`) or a python-can-remote server."""

    def __init__(
        self,
        channel: Any = None,
        can_filters: can.typechecking.CanFilters | None = None,
        receive_own_messages: bool = False,
        connect_timeout_s: float = CONNECT_TIMEOUT_S,
        **kwargs: Any,
    ) -> None:
        """Connect to the server at `channel` (ws://host:port/); CanInitializationError if not."""
        host, port, url = channel_url(channel)
        config: dict[str, Any] = {"receive_own_messages": bool(receive_own_messages)}
        config.update({k: v for k, v in kwargs.items() if isinstance(v, str | int | float | bool)})
        previous = socket.getdefaulttimeout()
        try:
            socket.setdefaulttimeout(connect_timeout_s)  # HTTPConnection takes no other
            websocket = WebSocket(url, [PROTOCOL])
            protocol = RemoteClientProtocol(config, websocket)
        except (OSError, AssertionError, can.CanError, ValueError) as exc:
            raise can.CanInitializationError(f"cannot connect to {url}: {exc}") from exc
        finally:
            socket.setdefaulttimeout(previous)
        self._sock: socket.socket = websocket.socket
        self._sock.settimeout(None)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buf = bytearray()
        self._pending: list[tuple[int, bytes]] = []
        self._send_lock = threading.Lock()
        self._batch: bytearray | None = None  # frames held for one write (`batch`)
        self._closed = False
        self.errors_from_server = 0
        self.channel_info = f"{protocol.channel_info}"
        self.url = url
        self.channel = url
        super().__init__(channel=url, can_filters=can_filters, **kwargs)
        logger.debug("connected to %s:%d (%s)", host, port, self.channel_info)

    def fileno(self) -> int:
        """The socket's file descriptor."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to the server (every other client receives it)."""
        data = ws_frame(_OP_BINARY, encode_message(msg), mask=True)
        try:
            with self._send_lock:
                if self._closed:
                    raise can.CanOperationError(f"{self.url}: bus is shut down")
                if self._batch is not None:
                    self._batch += data
                    return
                self._sock.sendall(data)
        except OSError as exc:
            raise can.CanOperationError(f"{self.url}: send failed: {exc}") from exc

    @contextlib.contextmanager
    def batch(self) -> Iterator[None]:
        """Hold the frames sent meanwhile (by any thread) and write them at the end, in order.

        A cycle's frames (a drive's TPDOs after a SYNC, a master's RPDOs and SYNC) then cross
        the socket and the relay in one write and one wake-up instead of one each. Nested
        batches write at the outermost end.
        """
        with self._send_lock:
            outer = self._batch is None
            if outer:
                self._batch = bytearray()
        try:
            yield
        finally:
            if outer:
                with self._send_lock:
                    data, self._batch = self._batch, None
                    if data and not self._closed:
                        try:
                            self._sock.sendall(data)
                        except OSError as exc:
                            raise can.CanOperationError(f"{self.url}: send failed: {exc}") from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            while self._pending:
                opcode, payload = self._pending.pop(0)
                msg = self._handle(opcode, payload)
                if msg is not None:
                    return msg, False
            remaining = None if deadline is None else max(0.0, deadline - time.monotonic())
            try:
                ready, _, _ = select.select([self._sock], [], [], remaining)
                if not ready:
                    return None, False
                chunk = self._sock.recv(_RECV_CHUNK)
            except (OSError, ValueError) as exc:
                raise can.CanOperationError(f"{self.url}: receive failed: {exc}") from exc
            if not chunk:
                raise can.CanOperationError(f"{self.url}: the server closed the connection")
            self._buf += chunk
            try:
                self._pending = parse_frames(self._buf)
            except ProtocolError as exc:
                raise can.CanOperationError(f"{self.url}: {exc}") from exc

    def _handle(self, opcode: int, payload: bytes) -> can.Message | None:
        if opcode == _OP_BINARY:
            try:
                return decode_message(payload, time.time())
            except ValueError as exc:
                logger.warning("%s: dropped a message: %s", self.url, exc)
                return None
        if opcode == _OP_PING:
            with self._send_lock:
                if not self._closed:
                    self._sock.sendall(ws_frame(_OP_PONG, payload, mask=True))
        elif opcode == _OP_CLOSE:
            raise can.CanOperationError(f"{self.url}: the server closed the connection")
        elif opcode == _OP_TEXT:
            self.errors_from_server += 1
            logger.warning("%s: server says %s", self.url, payload[:200].decode(errors="replace"))
        return None

    def shutdown(self) -> None:
        """Stop the periodic tasks, say goodbye to the server, close the socket."""
        if self._is_shutdown:
            return
        super().shutdown()  # stops the periodic tasks first
        with self._send_lock:
            if not self._closed:
                self._closed = True
                try:
                    self._sock.sendall(ws_frame(_OP_CLOSE, struct.pack(">H", 1000), mask=True))
                    self._sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                self._sock.close()


# --- the relay server: the console script `lca-can-server` ------------------------------------


@dataclass
class RelayStats:
    """What the relay did since it started."""

    connections: int = 0
    frames_in: int = 0
    frames_out: int = 0
    bad_messages: int = 0
    dropped_clients: int = 0


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
        self.host = host
        self.port: int = self._listener.getsockname()[1]

    @property
    def url(self) -> str:
        """The channel clients give: ws://host:port/."""
        return f"ws://{self.host}:{self.port}/"

    def stop(self) -> None:
        """Make `serve()` return (from any thread or a signal handler)."""
        self._stop.set()

    def serve(self, poll_s: float = 0.2) -> None:
        """Relay until `stop()`; then close every connection and the listener."""
        try:
            while not self._stop.is_set():
                for key, events in self._selector.select(poll_s):
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
            chunk = client.sock.recv(_RECV_CHUNK)
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
            if opcode == _OP_BINARY:
                self._relay(client, payload)
            elif opcode == _OP_TEXT:
                self._event(client, payload)
            elif opcode == _OP_PING:
                self._queue(client, ws_frame(_OP_PONG, payload))
            elif opcode == _OP_CLOSE:
                self._queue(client, ws_frame(_OP_CLOSE, payload[:2]))
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
            self._queue(client, ws_frame(_OP_TEXT, json.dumps(response).encode()))
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
        frame = ws_frame(_OP_BINARY, payload)
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


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="lca-can-server",
        description=(
            "Relay CAN frames between processes or machines, as one bus (python-can-remote's "
            f"websocket protocol). Clients: python-can interface {INTERFACE_NAME!r}, channel "
            "ws://HOST:PORT/. Runs until SIGINT or SIGTERM."
        ),
    )
    parser.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help=f"address to bind (default {DEFAULT_HOST}; 0.0.0.0 exposes it to the network)",
    )
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port, 0 = any (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--log-level", default="warning", choices=("debug", "info", "warning", "error")
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the relay until SIGINT/SIGTERM; 0 on a clean stop, 2 if it cannot bind."""
    args = _parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    try:
        server = RelayServer(args.host, args.port)
    except OSError as exc:
        print(
            f"lca-can-server: error: cannot listen on {args.host}:{args.port}: {exc}",
            file=sys.stderr,
        )
        return EXIT_BAD_INPUT

    def on_signal(signum: int, frame: FrameType | None) -> None:
        server.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    print(
        f"lca-can-server: relaying on {server.url}; SIGINT or SIGTERM stops",
        file=sys.stderr,
        flush=True,
    )
    server.serve()
    print(f"lca-can-server: stopped; {server.stats}", file=sys.stderr, flush=True)
    return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())


def batched_sends(bus: can.BusABC | None) -> contextlib.AbstractContextManager[None]:
    """`RemoteTransportBus.batch()` for a remote bus, nothing for any other.

    On a real interface each frame is its own write, as a CAN controller sends it.
    """
    if isinstance(bus, RemoteTransportBus):
        return bus.batch()
    return contextlib.nullcontext()
