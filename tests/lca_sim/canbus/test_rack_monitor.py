"""The rack's monitor (`lca_sim.canbus.rack_monitor`), realtime timing.

Few wake-ups while SYNCs come, the watchdogs on time when they stop, a silent master no freeze,
a freeze still discounted.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import canopen
import pytest
from support import Probe, emcy_code, rack_nmt, remote_node, sdo_enable, wait_until

from lca_sim.canbus.rack_monitor import MONITOR_PERIOD_S
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402.device import PowerState

PIVOT = 2
PERIOD_US = 4000  # 0x1006: a SYNC every 4 ms, SYNC loss after 10 periods (rack.yaml)
SYNC_LOSS_S = 10 * PERIOD_US * 1e-6
SCHEDULING_SLACK_S = 0.02  # a thread's wake-up on a shared 2-core machine


class SyncSender:
    """A master's SYNCs every 0x1006, on a thread; `silent` pauses them."""

    def __init__(self, probe: Probe) -> None:
        self._probe = probe
        self.silent = threading.Event()
        self._stop = threading.Event()
        self.last_sent_s = 0.0  # time.time() after the last SYNC went out (the bus's clock)
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(PERIOD_US * 1e-6):
            if not self.silent.is_set():
                self._probe.send(0x080)
                self.last_sent_s = time.time()

    def __enter__(self) -> SyncSender:
        self._thread.start()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self._stop.set()
        self._thread.join()


@pytest.fixture
def syncs(
    rack: VirtualDriveRack, probe: Probe, master: canopen.Network
) -> Iterator[tuple[SyncSender, canopen.RemoteNode]]:
    """The pivot OPERATIONAL with 0x1006 = 4 ms and SYNCs coming at that rate."""
    node = remote_node(master, PIVOT)
    node.sdo[0x1006].raw = PERIOD_US
    rack_nmt(rack, probe, 0x01, PIVOT, "OPERATIONAL")
    with SyncSender(probe) as sender:
        n = rack.counters.syncs
        wait_until(lambda: rack.counters.syncs > n + 10, "SYNCs flowing")
        yield sender, node


def test_while_syncs_come_the_thread_wakes_far_less_than_every_period(
    rack: VirtualDriveRack, syncs: tuple[SyncSender, canopen.RemoteNode]
) -> None:
    """Enabled (SYNC loss watched): about once per SYNC-loss time, not every 5 ms."""
    _, node = syncs
    sdo_enable(node)
    wakeups, n, start_s = rack.monitor_wakeups, rack.counters.syncs, time.monotonic()
    wait_until(lambda: rack.counters.syncs >= n + 250, "a second of SYNCs")
    per_period = (time.monotonic() - start_s) / MONITOR_PERIOD_S  # what a 5-ms tick did
    assert rack.monitor_wakeups - wakeups < 0.5 * per_period
    assert rack.counters.sync_losses == 0
    assert rack.power_state("pivot") is PowerState.OPERATION_ENABLED


def test_sync_loss_fires_within_its_deadline_and_a_period_when_syncs_stop(
    rack: VirtualDriveRack, probe: Probe, syncs: tuple[SyncSender, canopen.RemoteNode]
) -> None:
    """The thread slept while SYNCs came; the last one's deadline still wakes it on time."""
    sender, node = syncs
    sdo_enable(node)
    n = rack.counters.syncs
    wait_until(lambda: rack.counters.syncs >= n + 25, "SYNCs while enabled")
    mark = probe.mark()
    sender.silent.set()
    wait_until(lambda: bool(probe.seen(0x82, mark)), "the SYNC-loss EMCY")
    emcy = next(m for m in probe.frames[mark:] if m.arbitration_id == 0x82)
    assert emcy_code(bytes(emcy.data)) == (0x8700, 0x11)
    late_s = emcy.timestamp - sender.last_sent_s
    assert SYNC_LOSS_S < late_s <= SYNC_LOSS_S + MONITOR_PERIOD_S + SCHEDULING_SLACK_S
    assert rack.counters.sync_losses == 1


def test_a_master_silent_then_back_is_no_freeze_of_the_rack(
    rack: VirtualDriveRack, syncs: tuple[SyncSender, canopen.RemoteNode]
) -> None:
    """No SYNC for 0.2 s: the thread ticks every period meanwhile; the next SYNC is no freeze.

    The rack's process ran throughout: only the master was silent.
    """
    sender, _ = syncs
    freezes = rack.counters.process_freezes
    sender.silent.set()
    n = rack.counters.syncs
    wait_until(lambda: time.time() - sender.last_sent_s > 0.05, "the master silent")
    wakeups, start_s = rack.monitor_wakeups, time.monotonic()
    time.sleep(0.2)  # the master's silence under test: a stimulus, not a wait for a condition
    silent_periods = (time.monotonic() - start_s) / MONITOR_PERIOD_S
    assert rack.monitor_wakeups - wakeups > 0.5 * silent_periods  # its 5-ms period again
    sender.silent.clear()
    wait_until(lambda: rack.counters.syncs >= n + 25, "SYNCs again")
    assert rack.counters.process_freezes == freezes


def test_a_freeze_while_syncs_come_is_counted_and_discounted(
    rack: VirtualDriveRack, syncs: tuple[SyncSender, canopen.RemoteNode]
) -> None:
    """The rack's threads stand still 0.3 s while SYNCs queue: counted, no SYNC loss."""
    _, node = syncs
    sdo_enable(node)
    freezes = rack.counters.process_freezes
    with rack._lock:  # what a held GIL or a paused host does to the rack's threads
        time.sleep(0.3)  # the freeze under test: a stimulus, not a wait for a condition
    n = rack.counters.syncs
    wait_until(lambda: rack.counters.syncs >= n + 25, "SYNCs after the freeze")
    assert rack.counters.process_freezes > freezes
    assert rack.counters.sync_losses == 0
    assert rack.power_state("pivot") is PowerState.OPERATION_ENABLED
