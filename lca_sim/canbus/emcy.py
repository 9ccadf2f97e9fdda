"""EMCY error codes as text: what a master shows a person for a drive's emergency message.

The code classes (the high byte, or nibble) are CiA 301's table of emergency error codes
(CiA 301 v4.2 section 7.2.7.1, table 21); the specific codes are those of CiA 301 for the
communication errors (0x81xx, 0x82xx) and of CiA 402 part 2 (IEC 61800-7-201, annex on
error codes) for the drive's own errors, limited to the ones a servo drive commonly sends.
A code this table does not name is described by its class, which canopen's EmcyError knows,
with the code itself always printed beside the text. Device-specific codes (0xFF00-0xFFFF)
mean what each vendor says; the lca_hil virtual drive's own are named only for it.
"""

from __future__ import annotations

from canopen.emcy import EmcyError

from lca_sim.cia402 import device

# Specific codes: CiA 301 (communication) and CiA 402 (drive) emergency error codes.
SPECIFIC: dict[int, str] = {
    0x0000: "error reset or no error",
    0x1000: "generic error",
    0x2310: "continuous over-current",
    0x2320: "short circuit or earth leakage",
    0x3210: "DC link over-voltage",
    0x3220: "DC link under-voltage",
    0x4210: "excess temperature (device)",
    0x4310: "excess temperature (drive)",
    0x5530: "data storage error (non-volatile memory)",
    0x6320: "parameter error",
    0x7121: "motor blocked",
    0x7300: "sensor error",
    0x7305: "incremental sensor 1 fault",
    0x8100: "communication error (generic)",
    0x8110: "CAN overrun (objects lost)",
    0x8120: "CAN in error passive mode",
    0x8130: "life guard or heartbeat error",
    0x8140: "recovered from bus off",
    0x8150: "CAN-ID collision",
    0x8210: "PDO not processed due to length error",
    0x8220: "PDO length exceeded",
    0x8230: "DAM MPDO not processed, destination object not available",
    0x8240: "unexpected SYNC data length",
    0x8250: "RPDO timeout",
    0x8611: "following error",
    0x8612: "reference limit",
    0x8700: "sync controller error (no SYNC in time)",
    0x9000: "external error",
    0xFF00: "device specific",
}

# The lca_hil virtual drive's device-specific codes (docs/can.md, `lca_sim.cia402.device`).
LCA_DRIVE_SPECIFIC: dict[int, str] = {
    device.EMCY_LEFT_OPERATIONAL: "left NMT OPERATIONAL: the 0x6007 reaction acted",
    device.EMCY_PROCESS_STALL: "the drive's process stood still beyond its stall allowance",
}
# A second SYNC producer, as the lca_hil drive reports it (with the standard's generic code).
LCA_SYNC_TOO_FAST = "SYNC faster than the cycle period 0x1006: a second SYNC producer?"

# Codes that report a frame lost, rejected or late, or a stall, while the device goes on
# (CiA 301 7.2.7: the EMCY tells the master; the device's NMT and CiA 402 states do not change
# for them). A master reports them and does not stop the axes on them: a drive that does fault
# shows it in its statusword (fault bit 3) and sends its own code. A second SYNC producer
# (0x8100) is no such code: two masters on one bus, the axes stop.
ADVISORY = frozenset({0x8110, 0x8120, 0x8140, 0x8210, 0x8220, 0x8240})
LCA_DRIVE_ADVISORY = frozenset({device.EMCY_PROCESS_STALL})


def is_advisory(code: int, lca_drive: bool = False) -> bool:
    """Whether a master reports the code and lets the axes go on (`ADVISORY`)."""
    return code in ADVISORY or (lca_drive and code in LCA_DRIVE_ADVISORY)


def describe(code: int, lca_drive: bool = False) -> str:
    """'0x8130 life guard or heartbeat error': the code in hex and what it means.

    A code outside `SPECIFIC` gets the CiA 301 class of its high bits (e.g. 'Monitoring'),
    or 'unknown class' when not even that fits. `lca_drive`: the sender is lca_hil's virtual
    drive, whose device-specific codes have their own text.
    """
    text = None
    if lca_drive:
        text = LCA_DRIVE_SPECIFIC.get(code)
        if code == device.EMCY_SYNC_TOO_FAST:
            text = LCA_SYNC_TOO_FAST
    text = text or SPECIFIC.get(code)
    if text is None:
        cls = EmcyError(code, 0, b"", 0.0).get_desc()
        text = f"{cls.lower()} error" if cls else "unknown class"
    return f"0x{code:04X} {text}"
