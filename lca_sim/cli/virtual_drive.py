"""`lca-virtual-drive`: the virtual drive rack on a python-can interface, until SIGINT/SIGTERM.

    lca-virtual-drive --interface socketcan --channel vcan0 [--faults FILE]

Exit codes: 0 on a clean stop, 2 on a bad config or an interface that does not open.
docs/can.md, "The virtual drive rack".
"""

from __future__ import annotations

import argparse
import logging
import sys
import threading
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import can

from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.config.rack import TIMING_MODES, load_faults, load_rack_config
from lca_sim.errors import USER_ERRORS, fail
from lca_sim.runtime import GIL_SWITCH_INTERVAL_S, stop_signals


def _parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="lca-virtual-drive",
        description=(
            "Virtual CiA 402 drives (one CANopen node per axis of the lca_sim plant) on a CAN "
            "interface, until SIGINT or SIGTERM."
        ),
    )
    parser.add_argument("--interface", default="socketcan", help="python-can interface")
    parser.add_argument("--channel", default="can0", help="channel, e.g. can0 or vcan0")
    parser.add_argument("--bitrate", type=int, default=None, help="bit/s, where settable")
    parser.add_argument("--config", default=None, help="rack YAML (default: config/can/rack.yaml)")
    parser.add_argument(
        "--faults",
        default=None,
        help="YAML with a 'faults:' schedule, replacing the rack config's (docs/can.md)",
    )
    parser.add_argument(
        "--timing-mode",
        default=None,
        choices=TIMING_MODES,
        help="lockstep: the rack's time advances 0x1006 per SYNC only, every watchdog and "
        "heartbeat on it (the master is the clock); default: the rack config's (realtime)",
    )
    parser.add_argument(
        "--log-level", default="warning", choices=("debug", "info", "warning", "error")
    )
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Run a rack on a python-can interface until SIGINT/SIGTERM; 0 on a clean stop, 2 on error."""
    args = _parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(levelname)s %(name)s: %(message)s")
    prog = "lca-virtual-drive"
    try:
        config = load_rack_config(args.config)
        if args.faults is not None:
            config = load_faults(args.faults, config)
        if args.timing_mode is not None:
            config = replace(config, timing_mode=args.timing_mode)
    except USER_ERRORS as exc:
        return fail(prog, str(exc))
    kwargs: dict[str, Any] = {} if args.bitrate is None else {"bitrate": args.bitrate}
    try:
        bus = can.Bus(interface=args.interface, channel=args.channel, **kwargs)
    except (can.CanError, OSError, ValueError, ImportError, NotImplementedError) as exc:
        return fail(
            prog, f"cannot open CAN interface {args.interface!r} channel {args.channel!r}: {exc}"
        )
    # The rack answers each SYNC within a fraction of a period: a thread holding the GIL for
    # Python's default 5 ms would make it miss cycles (the bridge process sets the same).
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)
    stop = threading.Event()
    rack: VirtualDriveRack | None = None
    with stop_signals(lambda _name: stop.set()):
        try:
            rack = VirtualDriveRack(bus, config)
            rack.start()  # settles the heap first
            nodes = ", ".join(f"{a.name}={a.node_id}" for a in config.axes)
            print(
                f"{prog}: nodes {nodes} on {args.interface} {args.channel} "
                f"({config.timing_mode}); SIGINT or SIGTERM stops",
                file=sys.stderr,
                flush=True,
            )
            while not stop.wait(0.2):
                pass
        except USER_ERRORS as exc:
            return fail(prog, str(exc))
        finally:
            if rack is not None:
                rack.stop()
            bus.shutdown()
    return 0


if __name__ == "__main__":
    sys.exit(main())
