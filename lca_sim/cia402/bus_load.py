"""The load CAN frames put on a classical CAN bus: bits per frame, percent of the bit rate.

Pure arithmetic for bus-load budgets (docs/can.md, "The PDO layout the bridge maps").
"""

from __future__ import annotations


def frame_bits(data_bytes: int) -> int:
    """Bits on the wire of a classical CAN frame with an 11-bit identifier, worst-case stuffing.

    44 + 8 n bits of frame, 3 of interframe space, and one stuff bit per 4 of the 34 + 8 n
    bits that are stuffed (CiA / Bosch worst case, as used for bus-load budgets).
    """
    return 47 + 8 * data_bytes + (34 + 8 * data_bytes - 1) // 4


def frame_bits_nominal(data_bytes: int) -> int:
    """Bits on the wire of the same frame without stuffing (44 + 8 n, plus 3 of interframe)."""
    return 47 + 8 * data_bytes


# Both by data length, 0-64 bytes (every DLC python-can reports, CAN FD's too): a lookup for
# each frame the master counts.
FRAME_BITS: tuple[int, ...] = tuple(frame_bits(n) for n in range(65))
FRAME_BITS_NOMINAL: tuple[int, ...] = tuple(frame_bits_nominal(n) for n in range(65))


def bus_load_pct(bits_per_s: float, bitrate_bit_s: float) -> float:
    """Bus load in percent of the bit rate."""
    return 100.0 * bits_per_s / bitrate_bit_s
