"""One CAN frame onto a canopen network's bus, as canopen's `Network.send_message` sends it.

The master's cycle and the rack's TPDOs send several frames every SYNC; this is canopen's
`send_message` without its extra call and its `check` (each caller judges the notifier's error
its own way: the master raises it, the rack clears it).
"""

from __future__ import annotations

import can
import canopen


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
