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
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from typing import Any
from urllib.parse import urlsplit

import can

from lca_sim.canbus.data_frames import AttachedListeners, received_message
from lca_sim.canbus.linked_bus import LinkedVirtualBus
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
    decode_data_frame,
    decode_message,
    encode_message,
    masked_data_frames,
    parse_frames,
    ws_frame,
)

logger = logging.getLogger(__name__)
_BUS_LOGGER = logging.getLogger(can.bus.__name__)  # where `BusABC.recv` logs each frame

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
    """A python-can bus on a relay (`lca-can-server`) or a python-can-remote server.

    A read takes everything the socket has (the relay writes each sender's batch, a cycle's
    frames, at once) and turns it into frames stamped with the read's time; `recv` hands out
    the ones already read without touching the socket, filtered and logged as `BusABC.recv`
    does.
    """

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
            self._sock, channel_info, self._buf, pending = _connect(
                host, port, url, config, connect_timeout_s
            )
        except (OSError, ValueError, KeyError, TypeError, ProtocolError) as exc:
            raise can.CanInitializationError(f"cannot connect to {url}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._poller = select.poll()
        self._poller.register(self._sock, select.POLLIN)
        # Read, not yet handed out, in order: frames, runs of data frames for the attached
        # listeners (`attach`), and (opcode, payload) of the other websocket messages.
        self._ready: deque[can.Message | _DataRun | tuple[int, bytes]] = deque()
        self._attached: AttachedListeners | None = None
        self._send_lock = threading.Lock()
        self._batcher = _SendBatch(self)
        self._closed = False
        self._unfiltered = True  # no filters set: every frame passes (`_apply_filters`)
        # `BusABC.recv`'s log of each frame is on, as of the last read
        self._log_frames = _BUS_LOGGER.isEnabledFor(self.RECV_LOGGING_LEVEL)
        self.errors_from_server = 0
        self.channel_info = channel_info
        self.url = url
        self.channel = url
        self._queue_frames(pending, time.time())
        super().__init__(channel=url, can_filters=can_filters, **kwargs)
        logger.debug("connected to %s:%d (%s)", host, port, self.channel_info)

    def fileno(self) -> int:
        """The socket's file descriptor."""
        return self._sock.fileno()

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame to the server (every other client receives it)."""
        self._write(ws_frame(OP_BINARY, encode_message(msg), mask=True))

    def send_data_frame(self, arbitration_id: int, data: bytes) -> None:
        """`send` of a classical 11-bit data frame, without building its `can.Message`."""
        self._write(masked_data_frames(((arbitration_id, data),)))

    def send_data_frames(self, frames: Sequence[tuple[int, bytes]]) -> None:
        """`send_data_frame` of each frame, in order, in one write (a drive's TPDOs)."""
        self._write(masked_data_frames(frames))

    def _write(self, data: bytes) -> None:
        """Write one websocket frame, or hold it in the open batch."""
        try:
            with self._send_lock:
                if self._closed:
                    raise can.CanOperationError(f"{self.url}: bus is shut down")
                held = self._batcher.held
                if held is not None:
                    held += data
                    return
                self._sock.sendall(data)
        except OSError as exc:
            raise can.CanOperationError(f"{self.url}: send failed: {exc}") from exc

    def batch(self) -> contextlib.AbstractContextManager[None]:
        """Hold the frames sent meanwhile (by any thread) and write them at the end, in order.

        A cycle's frames (a drive's TPDOs after a SYNC, a master's RPDOs and SYNC) then cross
        the socket and the relay in one write and one wake-up instead of one each. While
        batches overlap (nested, or on other threads), the frames go out when the last ends.
        """
        return self._batcher

    def attach(self, listeners: Iterable[Callable[[can.Message], Any]]) -> None:
        """Hand the classical data frames read to `listeners` from `recv`'s thread, at once.

        Pass the list of the notifier that reads this bus (`can.Notifier.listeners`): the
        frames of one read go to a `DataFrameListener` (the rack's, the master's) in one call,
        without a message each, and to its other listeners as messages; `recv` returns the
        other frames (29-bit, remote, error, CAN FD), which the notifier hands on as before.
        Only while no filter is set and python-can's receive log is off: else every frame is
        a message from `recv`.
        """
        self._attached = AttachedListeners(listeners, self.channel)

    def detach(self) -> None:
        """Every frame from `recv` again (before the listeners go)."""
        self._attached = None

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """`BusABC.recv`: a frame read already comes at once, filtered and logged as there."""
        ready = self._ready
        while ready:
            item = ready.popleft()
            if isinstance(item, can.Message):
                if self._unfiltered or self._matches_filters(item):
                    if self._log_frames:
                        _BUS_LOGGER.log(self.RECV_LOGGING_LEVEL, "Received: %s", item)
                    return item
            elif isinstance(item, _DataRun):
                self._hand_on(item)
            else:
                self._handle(*item)
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        deadline = None if timeout is None else time.monotonic() + timeout
        wait_s = timeout
        ready = self._ready
        while True:
            while ready:
                item = ready.popleft()
                if isinstance(item, can.Message):
                    return item, False
                if isinstance(item, _DataRun):
                    self._hand_on(item)
                else:
                    self._handle(*item)
            if not self._read(wait_s):
                return None, False
            if deadline is not None:
                wait_s = max(deadline - time.monotonic(), 0.0)

    def _read(self, timeout_s: float | None) -> bool:
        """Read what the socket has, waiting up to `timeout_s` (None: for ever); False if none.

        poll, not select: one call into the kernel with no lists built, every cycle.
        """
        try:
            wait_ms = None if timeout_s is None else max(timeout_s, 0.0) * 1000.0
            if not self._poller.poll(wait_ms):
                return False
            chunk = self._sock.recv(RECV_CHUNK)
        except (OSError, ValueError) as exc:
            raise can.CanOperationError(f"{self.url}: receive failed: {exc}") from exc
        if not chunk:
            raise can.CanOperationError(f"{self.url}: the server closed the connection")
        self._buf += chunk
        try:
            frames = parse_frames(self._buf)
        except ProtocolError as exc:
            raise can.CanOperationError(f"{self.url}: {exc}") from exc
        self._log_frames = _BUS_LOGGER.isEnabledFor(self.RECV_LOGGING_LEVEL)
        self._queue_frames(frames, time.time())
        return True

    def _queue_frames(self, frames: list[tuple[int, bytes]], stamp_s: float) -> None:
        """Turn websocket messages into frames stamped `stamp_s`, the others kept for later.

        With listeners attached, no filter and no receive log, consecutive classical data
        frames become one run for the listeners (`attach`).
        """
        ready = self._ready
        runs = self._attached is not None and self._unfiltered and not self._log_frames
        run: _DataRun | None = None
        for opcode, payload in frames:
            if opcode != OP_BINARY:
                ready.append((opcode, payload))
                run = None
                continue
            if runs:
                frame = decode_data_frame(payload)
                if frame is not None:
                    if run is None:
                        run = _DataRun(stamp_s)
                        ready.append(run)
                    run.frames.append(frame)
                    continue
            run = None
            try:
                ready.append(decode_message(payload, stamp_s))
            except ValueError as exc:
                logger.warning("%s: dropped a message: %s", self.url, exc)

    def _hand_on(self, run: _DataRun) -> None:
        """A run of data frames to the attached listeners (as messages if they were detached)."""
        attached = self._attached
        if attached is not None:
            attached.data_frames(run.frames, run.stamp_s)
            return
        ready = self._ready  # detached since the read: back in front, each a message
        ready.extendleft(
            reversed([received_message(f, run.stamp_s, self.channel) for f in run.frames])
        )

    def _handle(self, opcode: int, payload: bytes) -> None:
        """A websocket message that is not a frame, in its turn among the frames."""
        if opcode == OP_PING:
            with self._send_lock:
                if not self._closed:
                    self._sock.sendall(ws_frame(OP_PONG, payload, mask=True))
        elif opcode == OP_CLOSE:
            raise can.CanOperationError(f"{self.url}: the server closed the connection")
        elif opcode == OP_TEXT:
            self.errors_from_server += 1
            logger.warning("%s: server says %s", self.url, payload[:200].decode(errors="replace"))

    def _apply_filters(self, filters: can.typechecking.CanFilters | None) -> None:
        """Filters stay python-can's (in software); this notes whether there are any."""
        self._unfiltered = filters is None

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


class _DataRun:
    """Consecutive classical data frames of one read, for the attached listeners."""

    __slots__ = ("frames", "stamp_s")

    def __init__(self, stamp_s: float) -> None:
        self.stamp_s = stamp_s
        self.frames: list[tuple[int, bytes]] = []


class _SendBatch:
    """`RemoteTransportBus.batch()`, one per bus: open batches counted, the last one writes."""

    __slots__ = ("_bus", "_open", "held")

    def __init__(self, bus: RemoteTransportBus) -> None:
        self._bus = bus
        self._open = 0
        self.held: bytearray | None = None  # the frames sent while a batch is open

    def __enter__(self) -> None:
        with self._bus._send_lock:
            if self.held is None:
                self.held = bytearray()
            self._open += 1

    def __exit__(self, *exc_info: object) -> None:
        bus = self._bus
        with bus._send_lock:
            self._open -= 1
            if self._open:
                return
            data, self.held = self.held, None
            if data and not bus._closed:
                try:
                    bus._sock.sendall(data)
                except OSError as exc:
                    raise can.CanOperationError(f"{bus.url}: send failed: {exc}") from exc


def batched_sends(bus: can.BusABC | None) -> contextlib.AbstractContextManager[None]:
    """`batch()` of a remote or linked bus (one write, one delivery), nothing for any other.

    On a real interface each frame is its own write, as a CAN controller sends it.
    """
    if isinstance(bus, RemoteTransportBus | LinkedVirtualBus):
        return bus.batch()
    return contextlib.nullcontext()
