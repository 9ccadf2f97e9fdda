"""The rack's object dictionary side: defaults, live objects, SDO reads and writes.

A part of the virtual drive rack that owns each drive's stored and computed object values and
the SDO server's callbacks; a write goes through here whether it came by SDO or RPDO, and is
refused with the CiA 301 abort code of docs/can.md, "The virtual drive rack".
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from canopen import SdoAbortedError
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from lca_sim.canbus.rack_cia402 import DriveControl
from lca_sim.canbus.rack_state import Drive, RackCounters
from lca_sim.cia402 import cia301, codec
from lca_sim.cia402 import device as cia402
from lca_sim.cia402 import objects as od
from lca_sim.cia402.codec import CodecError, DriveUnits
from lca_sim.cia402.mode_params import mode_write_abort
from lca_sim.config.rack import AxisConfig, RackConfig
from lca_sim.errors import ConfigError
from lca_sim.model.simulator import SIGNAL_NAMES

# Option codes: the values a write may set (others are refused with ABORT_VALUE_RANGE).
_OPTION_VALUES: dict[tuple[int, int], frozenset[int]] = {
    (od.ABORT_CONNECTION_OPTION, 0): cia402.ABORT_OPTIONS,
    (od.QUICK_STOP_OPTION, 0): cia402.QUICK_STOP_OPTIONS,
    (od.ERROR_BEHAVIOUR, 1): od.ERROR_BEHAVIOURS,
}


def drive_units(
    config: RackConfig, axis_config: AxisConfig, torque_constant_nm_per_a: float
) -> DriveUnits:
    """The axis's 0x6076 (k_t x rated current), 0x6075 and 0x608F, as a master reads them.

    Raises:
        ConfigError: a rated current the objects cannot hold.
    """
    try:
        return DriveUnits.from_raw(
            codec.RATED_TORQUE.encode(torque_constant_nm_per_a * axis_config.rated_current_a),
            codec.RATED_CURRENT.encode(axis_config.rated_current_a),
            config.encoder_increments_per_rev,
            1,
        )
    except CodecError as exc:
        raise ConfigError(
            config.source, f"axes.{axis_config.name}.rated_current_a", str(exc)
        ) from exc


class ObjectStore:
    """The objects of every drive of a rack: what a read returns, what a write does.

    Args:
        config: the rack's config (0x1017, 0x608F).
        arrays: the simulator's state, mode and signal arrays (views it updates in place).
        counters: the rack's counters (0x2020).
        longest_stall_s: the longest stall of this process so far (0x2021).
        control: the drives' CiA 402 part (0x6040, 0x6041, 0x6077).
        lock, clock: the rack's lock and clock (SDO requests come in the receive thread).
        write_fault: a write of 0x2030: (drive, subindex, value, now).
        write_pdo: a write of a PDO object: (drive, index, subindex, value) -> value to store.
    """

    def __init__(
        self,
        config: RackConfig,
        arrays: tuple[Any, Any, Any],
        counters: RackCounters,
        longest_stall_s: Callable[[], float],
        control: DriveControl,
        *,
        lock: threading.RLock,
        clock: Callable[[], float],
        write_fault: Callable[[Drive, int, int, float], None],
        write_pdo: Callable[[Drive, int, int, int], int],
    ) -> None:
        self._config = config
        self._state, self._modes, self._signals = arrays
        self._counters = counters
        self._longest_stall_s = longest_stall_s
        self._control = control
        self._lock = lock
        self._clock = clock
        self._write_fault = write_fault
        self._write_pdo = write_pdo

    def attach(self, axis: Drive) -> None:
        """Give a new drive its defaults and live objects, and serve its node's SDO requests."""
        axis.defaults = self._defaults(axis)
        axis.live = self._live_objects(axis)
        # canopen leaves these two unannotated.
        axis.node.add_read_callback(self._read_callback(axis))  # type: ignore[no-untyped-call]
        axis.node.add_write_callback(self._write_callback(axis))  # type: ignore[no-untyped-call]

    def _defaults(self, axis: Drive) -> dict[tuple[int, int], int]:
        values: dict[tuple[int, int], int] = {}
        for index in axis.od:
            entry = axis.od[index]
            members = (
                [entry[sub] for sub in entry] if isinstance(entry, ODRecord | ODArray) else [entry]
            )
            for var in members:
                if isinstance(var.default, int):
                    values[(var.index, var.subindex)] = var.default
        units = axis.units
        values[(od.HEARTBEAT_PRODUCER, 0)] = self._config.heartbeat_producer_ms
        values[(od.MOTOR_RATED_CURRENT, 0)] = codec.RATED_CURRENT.encode(units.rated_current_a)
        values[(od.MOTOR_RATED_TORQUE, 0)] = codec.RATED_TORQUE.encode(units.rated_torque_nm)
        values[(od.MAX_TORQUE, 0)] = axis.config.max_torque_permille
        values[(od.POSITION_ENCODER_RESOLUTION, 1)] = self._config.encoder_increments_per_rev
        values[(od.POSITION_ENCODER_RESOLUTION, 2)] = 1
        values[(od.SUPPORTED_DRIVE_MODES, 0)] = cia402.SUPPORTED_DRIVE_MODES_BITS
        # 0x607F: the drive loops' velocity cap (rack.yaml velocity_limit, joint side) in this
        # drive's increments/s, so a profile is clamped where its loops are: a faster profile
        # would run ahead of the axis into a following error.
        scale = codec.increments_per_joint_unit(units, axis.gear_ratio)
        values[(od.MAX_PROFILE_VELOCITY, 0)] = round(self._config.velocity_limit * scale)
        return values

    def _live_objects(self, axis: Drive) -> dict[tuple[int, int], Callable[[], int]]:
        """A getter per computed object, its codec bound once (TPDOs call these every SYNC).

        The plant's arrays are read-only views the simulator updates in place, so the getters
        read the state of the moment.
        """
        state, modes, signals = self._state, self._modes, self._signals
        control, counters = self._control, self._counters
        a, gear = axis.plant_index, axis.gear_ratio
        encode_position = codec.position(axis.units).encoder()
        loops, rad_per_increment = axis.modes, 2.0 * math.pi / axis.units.increments_per_rev
        encode_velocity = codec.velocity(axis.units).encoder()
        encode_current = codec.current(axis.units).encoder()
        encode_stall = codec.codec_for(od.entry(od.LONGEST_STALL)).encode
        live: dict[tuple[int, int], Callable[[], int]] = {
            (od.STATUSWORD, 0): lambda: control.statusword(axis),
            (od.CONTROLWORD, 0): lambda: axis.drive.controlword,
            (od.MODES_OF_OPERATION, 0): lambda: axis.drive.mode,
            (od.MODES_OF_OPERATION_DISPLAY, 0): lambda: axis.drive.mode,
            # Homing moves the position frame: 0x6064 reads 0x607C at home (`rack_modes`).
            (od.POSITION_ACTUAL, 0): lambda: encode_position(
                float(state[0, a]) * gear + loops.offset_inc * rad_per_increment
            ),
            (od.POSITION_DEMAND, 0): lambda: encode_position(loops.demand_inc * rad_per_increment),
            (od.FOLLOWING_ERROR_ACTUAL, 0): lambda: encode_position(
                loops.following_error_inc * rad_per_increment
            ),
            (od.VELOCITY_ACTUAL, 0): lambda: encode_velocity(float(state[1, a]) * gear),
            (od.TORQUE_ACTUAL, 0): lambda: control.torque_actual_permille(axis),
            (od.CURRENT_ACTUAL, 0): lambda: encode_current(float(state[2, a])),
            (od.DRIVE_STATE, 0): lambda: int(modes[1, a]),
            (od.MOTION_STATE, 0): lambda: int(modes[0, a]),
            (od.PROCESS_STALLS, 0): lambda: min(counters.process_freezes, 0xFFFFFFFF),
            (od.LONGEST_STALL, 0): lambda: encode_stall(self._longest_stall_s()),
            (od.FAULT_INJECTION, od.FAULT_LOST_TPDOS): lambda: axis.faults.lost_tpdos,
            (od.FAULT_INJECTION, od.FAULT_HEARTBEAT_OFF): lambda: int(axis.faults.heartbeat_off),
            (od.FAULT_INJECTION, od.FAULT_RAISE_EMCY): lambda: axis.faults.emcy_code,
            (od.FAULT_INJECTION, od.FAULT_DRIVE_FAULT): lambda: axis.faults.drive_fault,
            (od.FAULT_INJECTION, od.FAULT_BUS_OFF): lambda: (
                axis.faults.bus_off_ms or int(axis.faults.bus_off)
            ),
        }
        for name, obj in od.SIGNAL_OBJECTS.items():  # eta_m, eta_l, load torque, ...
            live[obj.key] = _signal_getter(
                signals, SIGNAL_NAMES.index(name), a, codec.codec_for(obj, axis.units).encoder()
            )
        return live

    def _read_callback(self, axis: Drive) -> Callable[..., int | None]:
        def on_read(*, index: int, subindex: int, od: ODVariable, **_: Any) -> int | None:
            if od.subindex != subindex:
                raise SdoAbortedError(cia301.ABORT_NO_SUBINDEX)
            with self._lock:
                live = axis.live.get((index, subindex))
                return live() if live is not None else axis.values.get((index, subindex))

        return on_read

    def _write_callback(self, axis: Drive) -> Callable[..., None]:
        def on_write(*, index: int, subindex: int, od: ODVariable, data: bytes, **_: Any) -> None:
            if od.subindex != subindex:
                raise SdoAbortedError(cia301.ABORT_NO_SUBINDEX)
            value = od.decode_raw(data)
            if not isinstance(value, int):
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            with self._lock:
                self.write(axis, index, subindex, value, self._clock())

        return on_write

    def write(self, axis: Drive, index: int, subindex: int, value: int, now: float) -> None:
        """Validate and apply a write (SDO or RPDO).

        Raises:
            SdoAbortedError: the write is refused (CiA 301 abort code).
        """
        if index == od.FAULT_INJECTION:
            self._write_fault(axis, subindex, value, now)
            return
        if index == od.CONTROLWORD:
            self._control.apply_controlword(axis, value, now)
            return
        if index == od.MODES_OF_OPERATION:
            if not cia402.is_supported_mode(value):
                raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
            axis.drive = replace(axis.drive, mode=value)
            return
        if index == od.MAX_TORQUE and value > axis.config.max_torque_permille:
            raise SdoAbortedError(cia301.ABORT_VALUE_TOO_HIGH)
        allowed = _OPTION_VALUES.get((index, subindex))
        if allowed is not None and value not in allowed:
            raise SdoAbortedError(cia301.ABORT_VALUE_RANGE)
        refused = mode_write_abort(index, subindex, value, axis.value)  # a mode's objects
        if refused is not None:
            raise SdoAbortedError(refused)
        value = self._write_pdo(axis, index, subindex, value)
        if index == od.HEARTBEAT_CONSUMER:
            axis.heartbeat_last_rx_s = None
        axis.values[(index, subindex)] = value


def _signal_getter(
    signals: Any, row: int, column: int, encode: Callable[[float], int]
) -> Callable[[], int]:
    """A getter encoding one plant signal of one axis (`SIGNAL_NAMES` row, axis column)."""

    def get() -> int:
        return encode(float(signals[row, column]))

    return get
