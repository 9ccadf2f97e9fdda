"""Benchmark: the CAN cycle of the bridge with four virtual CiA 402 drives, in CST.

For each cycle rate (250, 500 and 1000 Hz), in one process as `lca-can-bridge` runs it with
`interface: virtual`: the virtual drive rack (four CANopen nodes, one coupled lca_sim plant) on
one python-can virtual bus instance, the bridge's master (`lca_sim.canbus.master.Cia402Master`) on
another, the drives enabled in cyclic synchronous torque mode, and a stand-in controller that
answers every complete state with a current command (0.5 A on the pivot), as the controller node
does. Over a window of `--window-s` (10 s by default) it reports:

* on time: the share of cycles in which every drive's synchronous TPDOs arrived before the
  next SYNC, so a complete state went out in the cycle it belongs to;
* the latency from SYNC to the last TPDO of the cycle, p50 and p99;
* the bridge thread's period jitter (p50 and p99 of |period - 1/rate|);
* frames per second on the bus (both directions), and the load those frames would put on a
  1 Mbit/s classical CAN bus (worst-case bit stuffing, `lca_sim.cia402.master.frame_bits`).

Target: at least 99 % of cycles on time at 500 Hz. The script ends with one JSON line.

    .venv/bin/python bench/can_cycle.py            # 10 s per rate, about 40 s
    .venv/bin/python bench/can_cycle.py --quick    # 3 s per rate
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import sys
import time
from collections.abc import Sequence
from importlib import metadata
from typing import Any

import can
import canopen
import numpy as np

from lca_sim.canbus.master import GIL_SWITCH_INTERVAL_S, BridgeParams, Cia402Master, Snapshot
from lca_sim.canbus.virtual_rack import VirtualDriveRack, load_rack_config
from lca_sim.cia402.device import PowerState
from lca_sim.cia402.master import bus_load_pct
from lca_sim.cli.output import strict_json
from lca_sim.config.loader import config_dir, load_robot
from lca_sim.runtime import settle_heap

RATES_HZ = (250, 500, 1000)
TARGET_ON_TIME = 0.99
TARGET_RATE_HZ = 500
REFERENCE_BITRATE = 1_000_000.0
JOINTS = ("l_arm", "pivot", "c_arc", "lift")
COMMAND_A = [0.0, 0.5, 0.0, 0.0]
ENABLE_TIMEOUT_S = 10.0

JsonDict = dict[str, Any]


def percentile(values: Sequence[float], q: float) -> float:
    """The q-th percentile (numpy, linear interpolation); nan for no values."""
    return float(np.percentile(values, q)) if len(values) else math.nan


def rounded(value: float, digits: int = 3) -> float | None:
    """For the JSON line: None for non-finite values."""
    return round(value, digits) if math.isfinite(value) else None


def bridge_params(rate_hz: float) -> BridgeParams:
    """The bridge's figures for the shipped robot at `rate_hz`."""
    robot = load_robot("default")
    axes = {a.name: a for a in robot.axes}
    return BridgeParams(
        joints=JOINTS,
        node_ids=(1, 2, 3, 4),
        torque_constants_nm_per_a=tuple(axes[j].motor.torque_constant_nm_per_a for j in JOINTS),
        gear_ratios=tuple(axes[j].gear_ratio for j in JOINTS),
        drive_state_names=robot.state_machine.state_names,
        cycle_hz=rate_hz,
    )


def run_rate(rate_hz: int, window_s: float, warmup_s: float) -> JsonDict:
    """One rate: start rack and bridge, enable, measure a window, stop everything."""
    channel = f"bench_can_cycle_{rate_hz}_{os.getpid()}"
    rack_bus = can.Bus(interface="virtual", channel=channel)
    rack = VirtualDriveRack(rack_bus, load_rack_config(None))
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    bridge: Cia402Master | None = None
    try:
        rack.start()
        network.connect()

        def on_state(_snapshot: Snapshot) -> None:
            assert bridge is not None
            bridge.set_currents(COMMAND_A)

        bridge = Cia402Master(
            network, bridge_params(rate_hz), config_dir() / "can" / "lca_drive.eds", on_state
        )
        bridge.init()
        settle_heap()  # as the bridge node does before its cycle starts
        bridge.start()
        bridge.set_currents(COMMAND_A)
        bridge.enable(True)
        deadline = time.monotonic() + ENABLE_TIMEOUT_S
        while not all(
            bridge.axis_state(j).power_state is PowerState.OPERATION_ENABLED for j in JOINTS
        ):
            if time.monotonic() > deadline:
                return {"ok": False, "error": "drives not enabled"}
            time.sleep(0.01)
        time.sleep(warmup_s)  # a benchmark's warm-up, not a test's wait
        c = bridge.counters
        start = (c.cycles, c.complete_cycles, c.frames_sent + c.frames_received)
        bits0 = c.bits_sent + c.bits_received
        bridge.latencies_s.clear()
        bridge.cycle_starts_s.clear()
        bridge.keep_latencies = True
        t0 = time.monotonic()
        time.sleep(window_s)
        bridge.keep_latencies = False
        wall_s = time.monotonic() - t0
        cycles = c.cycles - start[0]
        complete = c.complete_cycles - start[1]
        frames = c.frames_sent + c.frames_received - start[2]
        bits = c.bits_sent + c.bits_received - bits0
        latencies_ms = [x * 1e3 for x in bridge.latencies_s]
        on_time = sum(1 for x in latencies_ms if x < 1e3 / rate_hz)
        periods = [b - a for a, b in itertools.pairwise(bridge.cycle_starts_s)]
        jitter_ms = [abs(p - 1.0 / rate_hz) * 1e3 for p in periods]
        return {
            "ok": True,
            "rate_hz": rate_hz,
            "achieved_hz": cycles / wall_s,
            "cycles": cycles,
            # On time: complete, and the last TPDO in before the next SYNC was due.
            "on_time_share": min(1.0, on_time / cycles) if cycles else math.nan,
            "complete_share": min(1.0, complete / cycles) if cycles else math.nan,
            "latency_p50_ms": percentile(latencies_ms, 50.0),
            "latency_p99_ms": percentile(latencies_ms, 99.0),
            "period_jitter_p50_ms": percentile(jitter_ms, 50.0),
            "period_jitter_p99_ms": percentile(jitter_ms, 99.0),
            "frames_per_s": frames / wall_s,
            "bus_load_pct_at_1mbit": bus_load_pct(bits / wall_s, REFERENCE_BITRATE),
            "send_failures": c.send_failures,
            "bad_pdos": c.bad_pdos,
            "latched": bridge.latched_reason(),
        }
    finally:
        rack.stop()  # first: a drive outliving the bridge would rightly report SYNC loss
        if bridge is not None:
            bridge.stop()
        network.disconnect()
        rack_bus.shutdown()


def main(argv: Sequence[str] | None = None) -> int:
    """Run every rate, print the figures, end with one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 s per rate")
    parser.add_argument("--window-s", type=float, default=None, help="seconds per rate")
    args = parser.parse_args(argv)
    window_s = args.window_s or (3.0 if args.quick else 10.0)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # as lca-can-bridge does
    warmup_s = 0.5 if args.quick else 1.0
    print(
        f"can_cycle benchmark: {window_s:g} s per rate, {os.cpu_count()} CPUs, "
        f"python {platform.python_version()}, python-can {can.__version__}, "
        f"canopen {metadata.version('canopen')}, virtual bus (in-process)"
    )
    results: dict[str, JsonDict] = {}
    for rate_hz in RATES_HZ:
        r = run_rate(rate_hz, window_s, warmup_s)
        results[str(rate_hz)] = r
        if not r.get("ok"):
            print(f"\n[{rate_hz} Hz] FAILED: {r.get('error')}")
            continue
        print(
            f"\n[{rate_hz} Hz] {r['cycles']} cycles ({r['achieved_hz']:.1f} Hz achieved)\n"
            f"  on time (every TPDO before the next SYNC)  {100 * r['on_time_share']:.2f} %\n"
            f"  SYNC -> last TPDO  p50 {r['latency_p50_ms']:.3f} ms, p99 "
            f"{r['latency_p99_ms']:.3f} ms\n"
            f"  cycle period jitter  p50 {r['period_jitter_p50_ms']:.3f} ms, p99 "
            f"{r['period_jitter_p99_ms']:.3f} ms\n"
            f"  {r['frames_per_s']:.0f} frames/s: {r['bus_load_pct_at_1mbit']:.1f} % of a "
            "1 Mbit/s bus" + (f"\n  latched: {r['latched']}" if r["latched"] else "")
        )
    target = results.get(str(TARGET_RATE_HZ), {})
    share = float(target.get("on_time_share", math.nan))
    met = share >= TARGET_ON_TIME if math.isfinite(share) else None
    print(
        f"\nsummary: {TARGET_RATE_HZ} Hz on time {100 * share:.2f} % (target >= "
        f"{100 * TARGET_ON_TIME:g} %: {'MET' if met else 'NOT MET'})"
    )
    record: JsonDict = {
        "bench": "can_cycle",
        "window_s": window_s,
        "target_on_time_share_at_500hz": TARGET_ON_TIME,
        "meets_target": met,
        "rates": {
            key: {k: (rounded(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
            for key, r in results.items()
        },
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
    }
    print(strict_json(record, indent=None))  # strict: NaN/inf as null, with why
    return 0 if all(r.get("ok") for r in results.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
