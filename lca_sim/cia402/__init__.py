"""Pure CANopen CiA 301 / CiA 402 logic: no bus, no clock, no file.

`objects` declares the object dictionary once (`object_entry` its entry types), `codec` its
units, `device` what a drive decides (power state machine, statusword, torque demand),
`sync_rate` which SYNCs come faster than 0x1006 allows, `master` what the bridge decides.
The profile and position modes: `profile` (the ramp), `mode_pp`, `mode_pv`, `homing`,
`mode_csp`, sharing `mode_common`; `mode_params` reads their objects (docs/can-modes.md).
"""
