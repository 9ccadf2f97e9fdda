"""The python-can interface `lca_remote`: a CAN bus on a relay (`lca-can-server`) over a websocket.

`can.Bus(interface="lca_remote", channel="ws://127.0.0.1:54701/")` (setup.py registers it under
the `can.interface` entry points). It opens the connection with python-can-remote's handshake
(an HTTP upgrade, then a JSON `bus_request` and `bus_response`), with a timeout on its own socket
only, and then reads and writes the socket itself, buffered. Periodic sends are python-can's
software ones (`BusABC.send_periodic`); filters are applied by `BusABC.recv`. It talks to a stock
`python -m can_remote` server too. docs/can-transport.md says why this and not python-can-
remote's own client; the wire format is in `wire.py`, the relay in `relay.py`.
"""

from __future__ import annotations

import base64
import contextlib
import json
import logging
import random
import select
import socket
import struct
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any
from urllib.parse import urlsplit

import can

from lca_sim.canbus.wire import (
    MAX_HTTP_REQUEST,
    OP_BINARY,
    OP_CLOSE,
    OP_PING,
    OP_PONG,
    OP_TEXT,
    PROTOCOL,
    RECV_CHUNK,
    ProtocolError,
    accept_key,
    channel_url,
    decode_message,
    encode_message,
    parse_frames,
    ws_frame,
)

logger = logging.getLogger(__name__)

INTERFACE_NAME = "lca_remote"
CONNECT_TIMEOUT_S = 5.0


def _connect(
    host: str, port: int, url: str, config: dict[str, Any], timeout_s: float
) -> tuple[socket.socket, str, bytearray, list[tuple[int, bytes]]]:
    """Open the websocket and join the bus: socket, channel info, unread bytes and frames.

    Every wait (connect, upgrade, `bus_response`) is bounded by `timeout_s` on this socket
    alone: a process-wide `socket.setdefaulttimeout` would reach every other thread's sockets
    meanwhile.
    """
    key = base64.b64encode(random.getrandbits(128).to_bytes(16, "little")).decode()
    request = (
        f"GET {urlsplit(url).path or '/'} HTTP/1.1\r\nHost: {host}:{port}\r\n"
        f"Accept-Encoding: identity\r\nUser-Agent: python-can/{can.__version__} ({sys.platform})"
        "\r\nUpgrade: WebSocket\r\nConnection: Upgrade\r\n"
        f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
        f"Sec-WebSocket-Protocol: {PROTOCOL}\r\n\r\n"
    )
    deadline = time.monotonic() + timeout_s
    sock = socket.create_connection((host, port), timeout=timeout_s)
    try:
        sock.sendall(request.encode("latin-1"))
        buf = bytearray()
        while (end := buf.find(b"\r\n\r\n")) < 0:
            if len(buf) > MAX_HTTP_REQUEST:
                raise ProtocolError("HTTP response too long")
            buf += _recv_before(sock, deadline)
        status, *lines = bytes(buf[:end]).decode("latin-1").split("\r\n")
        del buf[: end + 4]
        headers = {
            name.strip().lower(): value.strip()
            for name, sep, value in (line.partition(":") for line in lines)
            if sep
        }
        if status.split()[1:2] != ["101"] or headers.get("upgrade", "").lower() != "websocket":
            raise ProtocolError(f"no websocket upgrade: {status!r}")
        if headers.get("sec-websocket-accept") != accept_key(key):
            raise ProtocolError("wrong Sec-WebSocket-Accept")
        if headers.get("sec-websocket-protocol") != PROTOCOL:
            raise ProtocolError(f"subprotocol {headers.get('sec-websocket-protocol')!r}")
        bus_request = {"type": "bus_request", "payload": {"config": config}}
        sock.sendall(ws_frame(OP_TEXT, json.dumps(bus_request).encode(), mask=True))
        frames = parse_frames(buf)
        while not frames:
            buf += _recv_before(sock, deadline)
            frames = parse_frames(buf)
        (opcode, payload), *rest = frames
        event = json.loads(payload) if opcode == OP_TEXT else {}
        if event.get("type") != "bus_response":
            raise ProtocolError("the server did not answer the bus request")
        sock.settimeout(None)
    except BaseException:
        sock.close()
        raise
    return sock, f"{event['payload']['channel_info']} on {url}", buf, rest


def _recv_before(sock: socket.socket, deadline: float) -> bytes:
    """What the socket has, waiting no later than `deadline`; TimeoutError after it."""
    sock.settimeout(max(deadline - time.monotonic(), 1e-3))
    chunk = sock.recv(RECV_CHUNK)
    if not chunk:
        raise ProtocolError("the server closed the connection")
    return chunk


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
        try:
            self._sock, channel_info, self._buf, self._pending = _connect(
                host, port, url, config, connect_timeout_s
            )
        except (OSError, ValueError, KeyError, TypeError, ProtocolError) as exc:
            raise can.CanInitializationError(f"cannot connect to {url}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._send_lock = threading.Lock()
        self._batch: bytearray | None = None  # frames held for one write (`batch`)
        self._closed = False
        self.errors_from_server = 0
        self.channel_info = channel_info
        self.url = url
        self.channel = url
        super().__init__(channel=url, can_filters=can_filters, **kwargs)
        logger.debug("connected to %s:%d (%s)", host, port, self.channel_info)

    def fileno(self) -> int:
        """The socket's file descriptor."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to the server (every other client receives it)."""
        data = ws_frame(OP_BINARY, encode_message(msg), mask=True)
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
                chunk = self._sock.recv(RECV_CHUNK)
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
        if opcode == OP_BINARY:
            try:
                return decode_message(payload, time.time())
            except ValueError as exc:
                logger.warning("%s: dropped a message: %s", self.url, exc)
                return None
        if opcode == OP_PING:
            with self._send_lock:
                if not self._closed:
                    self._sock.sendall(ws_frame(OP_PONG, payload, mask=True))
        elif opcode == OP_CLOSE:
            raise can.CanOperationError(f"{self.url}: the server closed the connection")
        elif opcode == OP_TEXT:
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
                    self._sock.sendall(ws_frame(OP_CLOSE, struct.pack(">H", 1000), mask=True))
                    self._sock.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                self._sock.close()


def batched_sends(bus: can.BusABC | None) -> contextlib.AbstractContextManager[None]:
    """`RemoteTransportBus.batch()` for a remote bus, nothing for any other.

    On a real interface each frame is its own write, as a CAN controller sends it.
    """
    if isinstance(bus, RemoteTransportBus):
        return bus.batch()
    return contextlib.nullcontext()
