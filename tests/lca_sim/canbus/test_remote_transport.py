"""The cross-process CAN transport (`lca_sim.canbus.remote`): relay, interface, codec.

The end-to-end test runs what a user runs in three terminals, on 127.0.0.1: `lca-can-server`
and `lca-virtual-drive --interface lca_remote` as separate processes, the bridge's master
(`Cia402Master`) in this one. It boots, enables and moves the pivot with a current command, and
watches the drives' heartbeats across NMT commands (python-can-remote 0.3.0's own client lost
them at the first NMT state change). Nothing sleeps a fixed time: conditions are polled up to a
deadline, and every process started is stopped in the fixture's finally.
"""

from __future__ import annotations

import os
import random
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support import bridge_params, hold_stopped, wait_until

from lca_sim.canbus import remote, wire
from lca_sim.canbus.data_frames import DataFrames
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.relay import POLL_S, RelayServer
from lca_sim.cia402.device import PowerState
from lca_sim.cli import can_server
from lca_sim.config.paths import config_dir

BIN = Path(sys.executable).parent  # the console scripts sit next to the interpreter
EDS = config_dir() / "can" / "lca_drive.eds"
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
NODE_IDS = (1, 2, 3, 4)
START_TIMEOUT_S = 120.0  # a cold rack (numba, pinocchio) on a shared, loaded 2-core machine
NMT_PRE_OPERATIONAL_STATE = 0x7F
NMT_OPERATIONAL_STATE = 0x05


def _stop_process(proc: subprocess.Popen[str], timeout_s: float = 20.0) -> int:
    """SIGTERM, then SIGKILL after `timeout_s`; the exit code."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait(timeout_s)


def _read_line(proc: subprocess.Popen[str], pattern: str, timeout_s: float) -> re.Match[str]:
    """The first line of the process's stderr matching `pattern`, within `timeout_s`."""
    assert proc.stderr is not None
    deadline = time.monotonic() + timeout_s
    seen: list[str] = []
    while (left := deadline - time.monotonic()) > 0:
        ready, _, _ = select.select([proc.stderr], [], [], left)
        if not ready:
            break
        line = proc.stderr.readline()
        if not line:
            break
        seen.append(line)
        if match := re.search(pattern, line):
            return match
    pytest.fail(f"no line matching {pattern!r} within {timeout_s} s: {''.join(seen)[-2000:]}")


@pytest.fixture
def relay() -> Iterator[str]:
    """A `lca-can-server` process on 127.0.0.1, any free port: its channel URL."""
    proc = subprocess.Popen(
        [str(BIN / "lca-can-server"), "--port", "0"], stderr=subprocess.PIPE, text=True
    )
    try:
        yield _read_line(proc, r"ws://127\.0\.0\.1:\d+/", 30.0).group(0)
    finally:
        assert _stop_process(proc) == 0


@pytest.fixture
def in_process_relay() -> Iterator[RelayServer]:
    """A relay on a thread of this process (for the codec tests: cheap to start)."""
    server = RelayServer(port=0)
    thread = threading.Thread(target=server.serve, kwargs={"poll_s": 0.02}, daemon=True)
    thread.start()
    try:
        yield server
    finally:
        server.stop()
        thread.join(5.0)


@dataclass
class Heartbeats:
    """Every heartbeat seen on the bus: (time.monotonic(), node id, NMT state)."""

    seen: list[tuple[float, int, int]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message(self, msg: can.Message) -> None:
        """A Notifier listener: keep heartbeats (0x700 + id, one byte) of the rack's nodes."""
        node = msg.arbitration_id - 0x700
        if not msg.is_extended_id and node in NODE_IDS and len(msg.data) == 1:
            with self.lock:
                self.seen.append((time.monotonic(), node, msg.data[0] & 0x7F))

    def count(self, since: float, state: int) -> dict[int, int]:
        """Heartbeats per node after `since` reporting `state`."""
        with self.lock:
            counts = dict.fromkeys(NODE_IDS, 0)
            for t, node, s in self.seen:
                if t > since and s == state:
                    counts[node] += 1
            return counts

    def each_at_least(self, n: int, since: float, state: int) -> Callable[[], bool]:
        """A condition: every node sent at least `n` heartbeats in `state` after `since`."""
        return lambda: min(self.count(since, state).values()) >= n


def test_rack_and_master_in_separate_processes(relay: str) -> None:
    """Boot, enable, move the pivot both ways, stop; heartbeats survive NMT commands."""
    monitor = can.Bus(interface="lca_remote", channel=relay)
    heartbeats = Heartbeats()
    notifier = can.Notifier(monitor, [heartbeats.on_message])
    rack = subprocess.Popen(
        [str(BIN / "lca-virtual-drive"), "--interface", "lca_remote", "--channel", relay],
        stderr=subprocess.PIPE,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    network: canopen.Network | None = None
    bridge: Cia402Master | None = None
    try:
        t_boot = time.monotonic() - START_TIMEOUT_S
        wait_until(
            heartbeats.each_at_least(2, t_boot, NMT_PRE_OPERATIONAL_STATE),
            "every drive's heartbeat in PRE-OPERATIONAL over the relay",
            START_TIMEOUT_S,
        )
        network = canopen.Network(can.Bus(interface="lca_remote", channel=relay))
        network.connect()
        currents = [0.0] * 4
        snapshots: list[Snapshot] = []

        def on_state(snapshot: Snapshot) -> None:
            snapshots.append(snapshot)
            assert bridge is not None
            bridge.set_currents(currents)

        bridge = Cia402Master(network, bridge_params(), EDS, on_state=on_state)
        bridge.init()  # SDO configuration, then NMT start: every drive OPERATIONAL
        t_started = time.monotonic()
        bridge.start()
        # The heartbeat keeps coming after the NMT start (0x05 = OPERATIONAL), at its period.
        wait_until(
            heartbeats.each_at_least(10, t_started, NMT_OPERATIONAL_STATE),
            "10 OPERATIONAL heartbeats from every drive after NMT start",
            30.0,
        )
        assert time.monotonic() - t_started > 0.8  # 0x1017 = 100 ms: not a burst

        assert bridge.enable(True) == "enabling"
        wait_until(
            lambda: all(
                bridge.axis_state(j).power_state is PowerState.OPERATION_ENABLED for j in JOINTS
            ),
            "every drive OPERATION ENABLED",
            30.0,
        )
        for j in JOINTS:
            assert bridge.axis_state(j).statusword & 0x6F == 0x27  # CiA 402: operation enabled

        pivot = bridge.axis_state("pivot")
        p0 = pivot.position
        currents[1] = 3.0
        wait_until(
            lambda: bridge.axis_state("pivot").position > p0 + 0.01,
            "the pivot moving forward under +3 A",
            30.0,
        )
        assert abs(bridge.axis_state("pivot").current_a - 3.0) < 0.3
        p1 = bridge.axis_state("pivot").position
        currents[1] = -3.0
        wait_until(
            lambda: bridge.axis_state("pivot").position < p1 - 0.01,
            "the pivot moving back under -3 A",
            30.0,
        )
        assert abs(bridge.axis_state("pivot").current_a + 3.0) < 0.3
        for j in ("l_arm", "c_arc", "lift"):  # nothing commanded there
            assert abs(bridge.axis_state(j).current_a) < 0.05

        currents[1] = 0.0
        assert bridge.enable(False) == "disabling"
        wait_until(
            lambda: all(
                bridge.axis_state(j).power_state
                in (PowerState.READY_TO_SWITCH_ON, PowerState.SWITCH_ON_DISABLED)
                for j in JOINTS
            ),
            "every drive disabled",
            30.0,
        )
        assert abs(bridge.axis_state("pivot").current_a) < 0.05
        assert len(snapshots) > 50
        assert bridge.latched_reason() == ""
        # The master's heartbeat stops with its cycle: with CiA 301's 0x1029 default (0) the
        # drives would then leave OPERATIONAL on their own; this part is about the heartbeat.
        for j in JOINTS:
            bridge.sdo_write(j, 0x1029, 1, 1)
        bridge.stop()

        # NMT pre-operational and start again, broadcast: the heartbeat follows each state.
        t_pre = time.monotonic()
        monitor.send(can.Message(arbitration_id=0, is_extended_id=False, data=b"\x80\x00"))
        wait_until(
            heartbeats.each_at_least(5, t_pre, NMT_PRE_OPERATIONAL_STATE),
            "5 PRE-OPERATIONAL heartbeats from every drive after NMT enter pre-operational",
            30.0,
        )
        t_op = time.monotonic()
        monitor.send(can.Message(arbitration_id=0, is_extended_id=False, data=b"\x01\x00"))
        wait_until(
            heartbeats.each_at_least(5, t_op, NMT_OPERATIONAL_STATE),
            "5 OPERATIONAL heartbeats from every drive after NMT start",
            30.0,
        )
        assert rack.poll() is None, "the rack died"
    finally:
        if bridge is not None:
            bridge.stop()
        if network is not None:
            network.disconnect()
        notifier.stop()
        monitor.shutdown()
        code = _stop_process(rack)
        assert rack.stderr is not None
        rack_log = rack.stderr.read()
        rack.stderr.close()
    assert code == 0, rack_log[-3000:]


# --- frames cross unchanged --------------------------------------------------------------------

SPECIAL_FRAMES = [
    can.Message(arbitration_id=0x1ABCDEF0, is_extended_id=True, data=b"\x01\x02\x03"),
    can.Message(arbitration_id=0x123, is_extended_id=False, is_remote_frame=True, dlc=4),
    can.Message(arbitration_id=0x1FFFFFFF, is_extended_id=True, is_remote_frame=True, dlc=0),
    can.Message(
        arbitration_id=0x7FF,
        is_extended_id=False,
        is_fd=True,
        bitrate_switch=True,
        error_state_indicator=True,
        data=bytes(range(64)),
    ),
    can.Message(arbitration_id=0x000, is_extended_id=False, data=b""),
    can.Message(arbitration_id=0x040, is_extended_id=False, is_error_frame=True, data=bytes(8)),
]

frames = st.builds(
    lambda ext, rtr, fd, brs, esi, ident, data, dlc: can.Message(
        arbitration_id=ident & (0x1FFFFFFF if ext else 0x7FF),
        is_extended_id=ext,
        is_remote_frame=rtr and not fd,
        is_fd=fd,
        bitrate_switch=brs and fd,
        error_state_indicator=esi and fd,
        dlc=dlc if rtr and not fd else len(data),
        data=b"" if rtr and not fd else data,
    ),
    st.booleans(),
    st.booleans(),
    st.booleans(),
    st.booleans(),
    st.booleans(),
    st.integers(0, 0x1FFFFFFF),
    st.sampled_from([0, 1, 2, 3, 4, 5, 6, 7, 8, 12, 16, 20, 24, 32, 48, 64]).flatmap(
        lambda n: st.binary(min_size=n, max_size=n)
    ),
    st.integers(0, 8),
)


def _same(a: can.Message, b: can.Message) -> bool:
    return bool(a.equals(b, timestamp_delta=None, check_channel=False, check_direction=False))


@settings(max_examples=300, deadline=None)
@given(frames)
def test_codec_round_trip(msg: can.Message) -> None:
    """Every frame python-can can hold comes back from the payload unchanged."""
    back = wire.decode_message(wire.encode_message(msg), 12.5)
    assert _same(back, msg), (msg, back)
    assert back.timestamp == 12.5  # the receiver's clock, not the sender's


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(max_size=8))
def test_a_data_frame_encodes_as_its_message_would(arbitration_id: int, data: bytes) -> None:
    """The rack's TPDO send (`RemoteTransportBus.send_data_frame`): the bytes of `send`'s."""
    msg = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
    assert wire.encode_data_frame(arbitration_id, data) == wire.encode_message(msg)


@settings(max_examples=200, deadline=None)
@given(st.lists(frames, min_size=1, max_size=20), st.integers(1, 50), st.booleans())
def test_websocket_framing_survives_any_split(
    msgs: list[can.Message], chunk: int, masked: bool
) -> None:
    """Frames parsed from a stream cut at any points come out whole, masked or not."""
    stream = b"".join(wire.ws_frame(2, wire.encode_message(m), mask=masked) for m in msgs)
    buf = bytearray()
    got: list[tuple[int, bytes]] = []
    for i in range(0, len(stream), chunk):
        buf += stream[i : i + chunk]
        got += wire.parse_frames(buf)
    assert not buf
    assert [op for op, _ in got] == [2] * len(msgs)
    for (_, payload), msg in zip(got, msgs, strict=True):
        assert _same(wire.decode_message(payload, 0.0), msg)


@settings(max_examples=300, deadline=None)
@given(frames)
def test_only_classical_data_frames_decode_as_data_frames(msg: can.Message) -> None:
    """`decode_data_frame` takes a frame exactly when it is an 11-bit data frame of <= 8 bytes.

    And then as `decode_message` would: the same identifier and data.
    """
    payload = wire.encode_message(msg)
    frame = wire.decode_data_frame(payload)
    classical = not (
        msg.is_extended_id or msg.is_remote_frame or msg.is_error_frame or msg.is_fd
    ) and (msg.dlc == len(msg.data) <= 8)
    assert (frame is not None) == classical, (msg, frame)
    if frame is not None:
        assert frame == (msg.arbitration_id, bytes(msg.data))


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 0x7FF), st.binary(max_size=8)), min_size=1, max_size=12),
    st.integers(0, 2**32 - 1),
)
def test_masked_data_frames_are_the_client_frames_of_each(
    frames: list[tuple[int, bytes]], seed: int
) -> None:
    """One call gives the bytes of `ws_frame(..., mask=True)` of each frame, keys drawn alike.

    And a server reads them back as those frames (unmasked, each an 11-bit data frame).
    """
    random.seed(seed)
    batch = wire.masked_data_frames(frames)
    random.seed(seed)
    keys = random.getrandbits(32 * len(frames)).to_bytes(4 * len(frames), "little")
    unmasked = [wire.ws_frame(wire.OP_BINARY, wire.encode_data_frame(i, d)) for i, d in frames]
    one_by_one = b"".join(_masked(f, keys[4 * k : 4 * k + 4]) for k, f in enumerate(unmasked))
    assert batch == one_by_one
    parsed = wire.parse_frames(bytearray(batch))
    assert [wire.decode_data_frame(payload) for _, payload in parsed] == frames


def _masked(unmasked_frame: bytes, key: bytes) -> bytes:
    """A short unmasked websocket frame masked with `key` by RFC 6455 5.3's definition."""
    n = unmasked_frame[1]
    payload = unmasked_frame[2:]
    return (
        bytes((unmasked_frame[0], 0x80 | n))
        + key
        + bytes(b ^ key[j % 4] for j, b in enumerate(payload))
    )


class _Runs:
    """A `DataFrameListener` noting each call's frames (as the rack's and master's listeners)."""

    def __init__(self) -> None:
        self.runs: list[list[tuple[int, bytes]]] = []
        self.stamps: list[float] = []

    def __call__(self, msg: can.Message) -> None:
        raise AssertionError(f"a data frame came as a message: {msg}")

    def on_data_frames(self, frames: DataFrames, timestamp: float) -> None:
        self.runs.append(list(frames))
        self.stamps.append(timestamp)


def test_an_attached_bus_hands_a_read_s_data_frames_on_at_once(
    in_process_relay: RelayServer,
) -> None:
    """Over lca_remote: one call for the data frames of a read, the others from `recv` in turn.

    A message listener in the same list gets the data frames as messages; a 29-bit frame in
    the middle splits the run and comes out of `recv` between its two halves.
    """
    url = in_process_relay.url
    runs = _Runs()
    as_messages: list[can.Message] = []
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(interface="lca_remote", channel=url) as b,
    ):
        assert isinstance(b, remote.RemoteTransportBus)
        b.attach([runs, as_messages.append])
        data = [(0x201, b"\x0f\x00"), (0x202, b"\x0f\x00\x01\x02"), (0x80, b"")]
        extended = can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, data=b"\x01")
        before_s = time.time()
        with remote.batched_sends(a):
            for cob, payload in data[:2]:
                a.send(can.Message(arbitration_id=cob, is_extended_id=False, data=payload))
            a.send(extended)
            a.send(can.Message(arbitration_id=0x80, is_extended_id=False, data=b""))
        got = b.recv(10.0)
        assert got is not None and _same(got, extended)
        # the frames before it were handed on before it came out (in one run when the batch
        # came in one read, as it does on loopback; a split read makes two)
        assert [f for run in runs.runs for f in run] == data[:2]
        before_sync = len(runs.runs)
        assert b.recv(0.05) is None
        assert runs.runs[before_sync:] == [data[2:]]
        assert before_s <= runs.stamps[0] <= runs.stamps[-1] <= time.time()
        assert [(m.arbitration_id, bytes(m.data)) for m in as_messages] == data
        b.detach()
        a.send(can.Message(arbitration_id=0x181, is_extended_id=False, data=b"\x07"))
        back = b.recv(10.0)  # detached: every frame from recv again
        assert back is not None and back.arbitration_id == 0x181
        assert len(runs.runs) == before_sync + 1


def test_special_frames_cross_the_relay(in_process_relay: RelayServer) -> None:
    """29-bit, RTR, FD, error and 0-byte frames arrive unchanged and in order at the others."""
    url = in_process_relay.url
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(interface="lca_remote", channel=url) as b,
        can.Bus(interface="lca_remote", channel=url, receive_own_messages=True) as c,
    ):
        for msg in SPECIAL_FRAMES:
            a.send(msg)
        for bus in (b, c):
            for msg in SPECIAL_FRAMES:
                got = bus.recv(10.0)
                assert got is not None and _same(got, msg), (msg, got)
        c.send(SPECIAL_FRAMES[0])
        for bus in (a, b, c):  # c asked for its own frames back
            got = bus.recv(10.0)
            assert got is not None and _same(got, SPECIAL_FRAMES[0])
        assert a.recv(0.05) is None  # a did not: nothing else queued


def test_a_batch_is_one_write_and_arrives_whole_in_order(
    in_process_relay: RelayServer,
) -> None:
    """Frames sent in `batch()` reach nobody until it ends, then all of them, in order."""
    url = in_process_relay.url
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(interface="lca_remote", channel=url) as b,
    ):
        frames = [can.Message(arbitration_id=0x181 + k, data=bytes([k] * 8)) for k in range(5)]
        frames.append(can.Message(arbitration_id=0x80, data=b""))
        with remote.batched_sends(a):
            for msg in frames:
                a.send(msg)
            assert b.recv(0.2) is None  # held in a: nothing crossed the relay yet
            assert in_process_relay.stats.frames_in == 0
        for msg in frames:
            got = b.recv(10.0)
            assert got is not None and _same(got, msg), (msg, got)
        assert in_process_relay.stats.frames_in == len(frames)


def test_overlapping_batches_write_when_the_last_ends(in_process_relay: RelayServer) -> None:
    """A batch opened inside another holds its frames until the outer one ends too."""
    url = in_process_relay.url
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(interface="lca_remote", channel=url) as b,
    ):
        frames = [can.Message(arbitration_id=0x201 + k, data=bytes([k])) for k in range(3)]
        with remote.batched_sends(a):
            a.send(frames[0])
            with remote.batched_sends(a):
                a.send(frames[1])
            assert b.recv(0.2) is None  # the inner end wrote nothing
            a.send(frames[2])
        for msg in frames:
            got = b.recv(10.0)
            assert got is not None and _same(got, msg), (msg, got)


def test_frames_read_at_once_come_out_filtered_in_order_and_stamped(
    in_process_relay: RelayServer,
) -> None:
    """A batch's frames, read at once, pass the filters one by one, in order, stamped on read."""
    url = in_process_relay.url
    wanted = [{"can_id": 0x181, "can_mask": 0x7FF, "extended": False}]
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(interface="lca_remote", channel=url, can_filters=wanted) as b,
    ):
        sent = [
            can.Message(arbitration_id=0x181, is_extended_id=False, data=bytes([k]))
            for k in range(4)
        ]
        sent.insert(2, can.Message(arbitration_id=0x80, is_extended_id=False, data=b""))
        before_s = time.time()
        with remote.batched_sends(a):
            for msg in sent:
                a.send(msg)
        got = [b.recv(10.0) for _ in range(4)]
        after_s = time.time()
        assert b.recv(0.05) is None  # the SYNC was filtered out
        assert [bytes(m.data) for m in got if m is not None] == [bytes([k]) for k in range(4)]
        stamps = [m.timestamp for m in got if m is not None]
        assert stamps == sorted(stamps) and before_s <= stamps[0] and stamps[-1] <= after_s


def test_filters_and_periodic_send(in_process_relay: RelayServer) -> None:
    """python-can's own filters and software periodic send, with a data change mid-way."""
    url = in_process_relay.url
    with (
        can.Bus(interface="lca_remote", channel=url) as a,
        can.Bus(
            interface="lca_remote",
            channel=url,
            can_filters=[{"can_id": 0x701, "can_mask": 0x7FF, "extended": False}],
        ) as b,
    ):
        task = a.send_periodic(
            can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x7f"), 0.01
        )
        a.send(can.Message(arbitration_id=0x702, is_extended_id=False, data=b"\x7f"))
        first = b.recv(10.0)
        assert first is not None and first.arbitration_id == 0x701
        assert isinstance(task, can.ModifiableCyclicTaskABC)
        task.modify_data(can.Message(arbitration_id=0x701, is_extended_id=False, data=b"\x05"))
        deadline = time.monotonic() + 10.0
        seen: list[can.Message] = []
        while len([m for m in seen if m.data == b"\x05"]) < 5 and time.monotonic() < deadline:
            if (msg := b.recv(1.0)) is not None:
                seen.append(msg)
        assert len([m for m in seen if m.data == b"\x05"]) >= 5, seen
        assert all(m.arbitration_id == 0x701 for m in seen)  # 0x702 filtered out
        task.stop()


def test_stock_python_can_remote_client_joins(in_process_relay: RelayServer) -> None:
    """python-can-remote's own `remote` interface sends and receives through the relay."""
    url = in_process_relay.url
    with (
        can.Bus(interface="remote", channel=url) as stock,
        can.Bus(interface="lca_remote", channel=url) as ours,
    ):
        stock.send(SPECIAL_FRAMES[0])
        got = ours.recv(10.0)
        assert got is not None and _same(got, SPECIAL_FRAMES[0])
        ours.send(SPECIAL_FRAMES[3])
        got = stock.recv(10.0)
        assert got is not None and _same(got, SPECIAL_FRAMES[3])


def test_a_stalled_relay_says_how_long_every_frame_waited() -> None:
    """The relay's process stopped for 0.3 s: one warning with the stall, counted in its stats.

    A stall of the relay holds every frame on the bus, so the drives' watchdogs may fire with
    no node silent; the relay is the only process that can tell (its `select` returns further
    apart than its poll period).
    """
    stall_s = 0.3
    proc = subprocess.Popen(
        [str(BIN / "lca-can-server"), "--port", "0"], stderr=subprocess.PIPE, text=True
    )
    try:
        _read_line(proc, r"relaying on ws://127\.0\.0\.1:\d+/", 30.0)
        hold_stopped(proc, stall_s)  # the relay gets no CPU for stall_s, as on a paused host
        proc.send_signal(signal.SIGCONT)
        warned = _read_line(proc, r"WARNING .*relay: this process stood still for (\d+) ms", 30.0)
    finally:
        proc.send_signal(signal.SIGCONT)
        code = _stop_process(proc)
    assert code == 0
    # at least the stall, less the one poll period the relay could have been waiting anyway
    assert int(warned.group(1)) >= (stall_s - POLL_S) * 1e3, warned.group(0)
    assert "longer than the deadline (0.1 s); every frame on the bus waited as long" in (
        warned.string
    )
    assert proc.stderr is not None
    stats = proc.stderr.read()
    counted = re.search(r"freezes=(\d+), longest_freeze_s=([0-9.]+)", stats)
    assert counted is not None, stats
    # this stall, and any scheduling hiccup of a loaded host beside it (counted, not logged)
    assert int(counted.group(1)) >= 1 and float(counted.group(2)) >= stall_s - POLL_S, stats


def test_no_server_is_an_init_error() -> None:
    server = RelayServer(port=0)  # bound, so the port is free of anyone else's server
    port = server.port
    server.stop()
    server.serve()  # returns at once and closes the listener
    with pytest.raises(can.CanInitializationError):
        can.Bus(interface="lca_remote", channel=f"127.0.0.1:{port}")


def test_binds_loopback_by_default() -> None:
    assert wire.DEFAULT_HOST == "127.0.0.1"
    args = can_server._parse_args([])
    assert args.host == "127.0.0.1"
    assert wire.channel_url("127.0.0.1") == ("127.0.0.1", 54701, "ws://127.0.0.1:54701/")


def test_connect_leaves_the_process_socket_default_alone(
    monkeypatch: pytest.MonkeyPatch, in_process_relay: RelayServer
) -> None:
    """The connect timeout is the bus's socket's own: `socket.setdefaulttimeout` is never called."""
    calls: list[float | None] = []
    monkeypatch.setattr(socket, "setdefaulttimeout", calls.append)
    with can.Bus(interface="lca_remote", channel=in_process_relay.url, connect_timeout_s=3.0):
        pass
    assert calls == []


def test_a_hanging_connect_times_out_alone() -> None:
    """While a connect waits on a server that never answers, other threads keep no timeout."""
    listener = socket.create_server(("127.0.0.1", 0))  # accepts into its backlog, never replies
    port = listener.getsockname()[1]
    errors: list[BaseException] = []

    def connect() -> None:
        try:
            can.Bus(interface="lca_remote", channel=f"127.0.0.1:{port}", connect_timeout_s=2.0)
        except can.CanInitializationError as exc:
            errors.append(exc)

    waiting = threading.Thread(target=connect)
    waiting.start()
    try:
        while waiting.is_alive():
            assert socket.getdefaulttimeout() is None
            waiting.join(0.01)
    finally:
        waiting.join()
        listener.close()
    assert len(errors) == 1  # the bus's own timeout ended the wait
