"""A CAN frame onto a canopen network's bus; a bus whose receive fails, as a listener takes it.

The master's cycle and the rack's TPDOs send several frames every SYNC; this is canopen's
`send_message` without its extra call and its `check` (each caller judges the notifier's error
its own way: the master raises it, the rack clears it). `ReceiveFailures` is how the master's
and the rack's listeners handle the notifier's receive errors.
"""

from __future__ import annotations

import math
import time

import can
import canopen

# A bus whose receive keeps failing (its interface down, the lca_remote relay gone) is tried
# again this often by the notifier's thread, instead of in a tight loop.
RECEIVE_RETRY_S = 0.1


def send_frame(network: canopen.Network, can_id: int, data: bytes, remote: bool = False) -> None:
    """Send one frame on `network`'s bus under canopen's `send_lock` (its SDO client's too).

    Raises:
        RuntimeError: the network is not connected (canopen's error).
        can.CanError: the bus refused the frame.
    """
    bus = network.bus
    if bus is None:
        raise RuntimeError("Not connected to CAN bus")
    msg = can.Message(
        is_extended_id=can_id > 0x7FF, arbitration_id=can_id, data=data, is_remote_frame=remote
    )
    with network.send_lock:
        bus.send(msg)


class ReceiveFailures:
    """A bus's failing receives, as a listener's `on_error` takes them from python-can's notifier.

    Unless a listener handles it, an exception of the bus's `recv` ends the notifier's thread
    with a bare traceback, and canopen's `Network.check` re-raises it at every later send: the
    node stops hearing the bus and says nothing a person reads. Handled through `failed`, the
    failure is counted, the notifier's kept exception is cleared (sends go on), and the thread
    tries the bus again: at once after a single failure (a malformed datagram), after
    `RECEIVE_RETRY_S` when failures follow each other (a bus that stays broken), so that an
    interface that comes back up is heard again without a restart and a broken one costs no CPU.
    """

    def __init__(self) -> None:
        self.count = 0
        self.last = ""  # the last failure's text
        self.last_t = -math.inf  # time.monotonic() of the last failure

    def failed(self, exc: Exception, notifier: can.Notifier | None) -> bool:
        """Count `exc` (called in the notifier's thread); True when it begins a run of failures."""
        now = time.monotonic()
        again = now - self.last_t < 2.0 * RECEIVE_RETRY_S
        self.count += 1
        self.last = str(exc) or type(exc).__name__
        self.last_t = now
        if notifier is not None:
            notifier.exception = None  # or canopen's next send re-raises it
        if again:
            time.sleep(RECEIVE_RETRY_S)  # the notifier's thread: the next try a retry later
        return not again

    def failing(self, now_s: float) -> bool:
        """A failure within the last three retry periods: the bus is not heard now."""
        return now_s - self.last_t < 3.0 * RECEIVE_RETRY_S
