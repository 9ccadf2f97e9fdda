"""CiA 301 (CANopen application layer) numbers the drives and the master share on the bus.

COB-IDs of the pre-defined connection set, NMT command and state codes, SDO abort codes; the
object table beside it (`objects.py`) holds the objects. See docs/can.md for how they are used.
"""

from __future__ import annotations

# --- COB-IDs: the pre-defined connection set (CiA 301 7.3.5, tables 72 and 73) ---------------
NMT_COB_ID = 0x000  # NMT module control, broadcast: 2 bytes, command and node id (0: all)
SYNC_COB_ID = 0x080  # default of 0x1005 (COB-ID SYNC); SYNC without a counter has no data
EMCY_COB_BASE = 0x080  # + node id: default of 0x1014 (COB-ID EMCY)
TPDO_COB_BASES = (0x180, 0x280, 0x380, 0x480)  # + node id: TPDO1-4, defaults of 0x1800-0x1803
RPDO_COB_BASES = (0x200, 0x300, 0x400, 0x500)  # + node id: RPDO1-4, defaults of 0x1400-0x1403
SDO_RESPONSE_COB_BASE = 0x580  # + node id: SDO server -> client
SDO_REQUEST_COB_BASE = 0x600  # + node id: SDO client -> server
HEARTBEAT_COB_BASE = 0x700  # + node id: NMT error control (boot-up, heartbeat)
NODE_ID_MAX = 0x7F  # node ids are 1-127

# --- NMT module control command specifiers (CiA 301 7.2.8.3.1) --------------------------------
NMT_START = 0x01  # start remote node: to OPERATIONAL
NMT_STOP = 0x02  # stop remote node: to STOPPED
NMT_ENTER_PRE_OPERATIONAL = 0x80
NMT_RESET_NODE = 0x81
NMT_RESET_COMMUNICATION = 0x82

# --- NMT states as the heartbeat's one byte carries them (CiA 301 7.2.8.3.2.2) -----------------
NMT_STATE_BOOT_UP = 0x00
NMT_STATE_STOPPED = 0x04
NMT_STATE_OPERATIONAL = 0x05
NMT_STATE_PRE_OPERATIONAL = 0x7F

# --- SDO abort codes the drives answer with (CiA 301 7.2.4.3.17, table 22) --------------------
ABORT_NOT_MAPPABLE = 0x06040041  # object cannot be mapped to the PDO
ABORT_PDO_LENGTH = 0x06040042  # number and length of mapped objects exceed the PDO length
ABORT_NO_SUBINDEX = 0x06090011  # sub-index does not exist
ABORT_VALUE_RANGE = 0x06090030  # value range of parameter exceeded (write access only)
ABORT_VALUE_TOO_HIGH = 0x06090031  # value of parameter written too high
ABORT_VALUE_TOO_LOW = 0x06090032  # value of parameter written too low
ABORT_MAX_BELOW_MIN = 0x06090036  # maximum value is less than minimum value
ABORT_DEVICE_STATE = 0x08000022  # data cannot be transferred because of the present device state
