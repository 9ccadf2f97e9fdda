"""Bus load of classical CAN frames (`lca_sim.cia402.bus_load`)."""

from __future__ import annotations

import pytest

from lca_sim.cia402 import bus_load


def test_frame_bits_and_bus_load_of_four_axes() -> None:
    assert bus_load.frame_bits(0) == 55  # SYNC
    assert bus_load.frame_bits(8) == 135  # the classic worst case of an 8-byte standard frame
    # Per cycle: SYNC, 4 RPDO1 (4 bytes), 4 TPDO1 (6), 4 TPDO2 (6): docs/can.md's mapping.
    bits = bus_load.frame_bits(0) + 4 * (bus_load.frame_bits(4) + 2 * bus_load.frame_bits(6))
    assert bits == 55 + 4 * (95 + 2 * 115)
    assert bus_load.bus_load_pct(bits * 500, 1e6) == pytest.approx(67.75)
    assert bus_load.bus_load_pct(bits * 1000, 1e6) > 100.0  # 1 kHz does not fit on 1 Mbit/s
