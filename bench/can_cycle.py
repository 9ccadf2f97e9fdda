"""Benchmark: the CAN cycle of the bridge with four virtual CiA 402 drives, in CST.

For each cycle rate (250, 500 and 1000 Hz) and each mode, the bridge's master
(`lca_sim.canbus.master.Cia402Master`) in this process with the drives enabled in cyclic
synchronous torque mode, and a stand-in controller that answers every complete state with a
current command (0.5 A on the pivot), as the controller node does, against the virtual drive rack
(four CANopen nodes, one coupled lca_sim plant):

* in-process: as `lca-can-bridge` runs it with `interface: virtual`, the rack on one linked
  virtual bus of this process, the master on another (`LinkedVirtualBus`: a cycle is one call
  in the master's thread; one GIL for both);
* cross-process: as the three-terminal recipe of docs/can-transport.md runs it, the relay
  `lca-can-server` and the rack `lca-virtual-drive --interface lca_remote` as two more processes
  on 127.0.0.1, the master on `interface: lca_remote`. It also reports the CPU each process used
  in the window (% of one core), which says which part of the cycle costs what.

Over a window of `--window-s` (10 s by default) it reports:

* on time: the share of cycles in which every drive's synchronous TPDOs arrived before the
  next SYNC, so a complete state went out in the cycle it belongs to;
* the latency from SYNC to the last TPDO of the cycle, p50 and p99;
* the bridge thread's period jitter (p50 and p99 of |period - 1/rate|);
* frames per second on the bus (both directions), and the load those frames would put on a
  1 Mbit/s classical CAN bus (worst-case bit stuffing, `lca_sim.cia402.bus_load.frame_bits`).

Targets: at least 99 % of cycles on time at 500 Hz (both modes), and cross-process at least 95 %
at 1000 Hz. The script ends with one JSON line holding both modes.

    .venv/bin/python bench/can_cycle.py                        # 10 s per rate and mode
    .venv/bin/python bench/can_cycle.py --quick                # 3 s per rate and mode
    .venv/bin/python bench/can_cycle.py --mode cross-process   # one mode only
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import platform
import re
import select
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from importlib import metadata
from pathlib import Path
from typing import Any

import can
import numpy as np

from lca_sim.canbus.linked_bus import LinkedVirtualBus
from lca_sim.canbus.master import Cia402Master
from lca_sim.canbus.master_frames import master_network
from lca_sim.canbus.master_params import BridgeParams
from lca_sim.canbus.master_state import Snapshot
from lca_sim.canbus.virtual_rack import VirtualDriveRack
from lca_sim.cia402.bus_load import bus_load_pct
from lca_sim.cia402.device import PowerState
from lca_sim.config.loader import load_robot
from lca_sim.config.paths import config_dir
from lca_sim.config.rack import load_rack_config
from lca_sim.output import strict_json
from lca_sim.runtime import GIL_SWITCH_INTERVAL_S, settle_heap

RATES_HZ = (250, 500, 1000)
MODES = ("in-process", "cross-process")
# (mode, rate) -> the least share of cycles on time (issue 15's targets).
TARGETS = {("in-process", 500): 0.99, ("cross-process", 500): 0.99, ("cross-process", 1000): 0.95}
TARGET_ON_TIME = 0.99
TARGET_RATE_HZ = 500
BIN = Path(sys.executable).parent  # the console scripts sit next to the interpreter
START_TIMEOUT_S = 120.0  # a cold rack process (numba, pinocchio) on a loaded machine
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


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far; nan where /proc is not there."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return math.nan
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _stderr_line(proc: subprocess.Popen[str], pattern: str, timeout_s: float) -> str:
    """The first stderr line of `proc` matching `pattern`; RuntimeError after `timeout_s`."""
    assert proc.stderr is not None
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        if not select.select([proc.stderr], [], [], left)[0]:
            break
        line = proc.stderr.readline()
        if not line:
            break
        if re.search(pattern, line):
            return line
    raise RuntimeError(f"process {proc.pid}: no {pattern!r} on stderr within {timeout_s} s")


def _stop(proc: subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(20.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    if proc.stderr is not None:
        proc.stderr.close()


# The master's bus, the pids whose CPU to report, and a stop for the rack (idempotent).
Rig = tuple[can.BusABC, dict[str, int], Callable[[], None]]


@contextmanager
def in_process_rack(rate_hz: int, switch_interval_s: float | None = None) -> Iterator[Rig]:
    """The rack on a linked virtual bus of this process; the master's, as the bridge opens both."""
    channel = f"bench_can_cycle_{rate_hz}_{os.getpid()}"
    rack_bus = LinkedVirtualBus(channel=channel)
    rack = VirtualDriveRack(rack_bus, load_rack_config(None))
    try:
        rack.start()
        yield LinkedVirtualBus(channel=channel), {}, rack.stop
    finally:
        rack.stop()  # first: a drive outliving the bridge would rightly report SYNC loss
        rack_bus.shutdown()


def rack_command(switch_interval_s: float | None) -> list[str]:
    """The rack's command line: `lca-virtual-drive` as installed, or its main() after a switch.

    With `switch_interval_s`, `sys.setswitchinterval` runs first: what the rack would do if it
    set it as `lca-can-bridge` does.
    """
    if switch_interval_s is None:
        return [str(BIN / "lca-virtual-drive")]
    code = (
        f"import sys; sys.setswitchinterval({switch_interval_s!r}); "
        "from lca_sim.cli.virtual_drive import main; sys.exit(main())"
    )
    return [sys.executable, "-c", code]


@contextmanager
def cross_process_rack(rate_hz: int, switch_interval_s: float | None = None) -> Iterator[Rig]:
    """`lca-can-server` and `lca-virtual-drive` processes on 127.0.0.1; the master's bus."""
    procs: list[subprocess.Popen[str]] = []
    try:
        server = subprocess.Popen(
            [str(BIN / "lca-can-server"), "--port", "0"], stderr=subprocess.PIPE, text=True
        )
        procs.append(server)
        line = _stderr_line(server, r"ws://127\.0\.0\.1:\d+/", 30.0)
        url = re.search(r"ws://\S+/", line).group(0)  # type: ignore[union-attr]
        rack = subprocess.Popen(
            [*rack_command(switch_interval_s), "--interface", "lca_remote", "--channel", url],
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        procs.append(rack)
        _stderr_line(rack, r"lca-virtual-drive: nodes", START_TIMEOUT_S)
        master_bus = can.Bus(interface="lca_remote", channel=url)
        yield master_bus, {"relay": server.pid, "rack": rack.pid}, lambda: _stop(rack)
    finally:
        for proc in reversed(procs):  # the rack first, as in-process
            _stop(proc)


def run_rate(
    rate_hz: int,
    window_s: float,
    warmup_s: float,
    mode: str = "in-process",
    rack_switch_interval_s: float | None = None,
) -> JsonDict:
    """One rate: start rack and bridge, enable, measure a window, stop everything."""
    rig = cross_process_rack if mode == "cross-process" else in_process_rack
    try:
        with rig(rate_hz, rack_switch_interval_s) as (master_bus, pids, stop_rack):
            return _measure(master_bus, pids, stop_rack, rate_hz, window_s, warmup_s)
    except (RuntimeError, OSError, can.CanError) as exc:
        return {"ok": False, "error": f"{type(exc).__name__}: {exc}"}


def _measure(
    master_bus: can.BusABC,
    pids: dict[str, int],
    stop_rack: Callable[[], None],
    rate_hz: int,
    window_s: float,
    warmup_s: float,
) -> JsonDict:
    network = master_network(master_bus)  # the bridge's: linked or lca_remote, attached
    bridge: Cia402Master | None = None
    try:

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
        pids = {"bridge": os.getpid(), **pids}
        cpu0 = {name: _cpu_s(pid) for name, pid in pids.items()}
        c = bridge.counters
        start = (c.cycles, c.complete_cycles, c.frames_sent + c.frames_received)
        bits0 = c.bits_sent + c.bits_received
        nominal0 = c.nominal_bits
        bridge.latencies_s.clear()
        bridge.cycle_starts_s.clear()
        bridge.keep_latencies = True
        t0 = time.monotonic()
        time.sleep(window_s)
        bridge.keep_latencies = False
        wall_s = time.monotonic() - t0
        cpu_pct = {name: 100.0 * (_cpu_s(pid) - cpu0[name]) / wall_s for name, pid in pids.items()}
        cycles = c.cycles - start[0]
        complete = c.complete_cycles - start[1]
        frames = c.frames_sent + c.frames_received - start[2]
        bits = c.bits_sent + c.bits_received - bits0
        nominal_bits = c.nominal_bits - nominal0
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
            # Worst-case bit stuffing (the budget figure) and no stuffing, of 1 Mbit/s.
            "bus_load_pct_at_1mbit": bus_load_pct(bits / wall_s, REFERENCE_BITRATE),
            "bus_load_nominal_pct_at_1mbit": bus_load_pct(nominal_bits / wall_s, REFERENCE_BITRATE),
            "send_failures": c.send_failures,
            "bad_pdos": c.bad_pdos,
            "latched": bridge.latched_reason(),
            # CPU used in the window, % of one core, per process (this one: the bridge).
            **{f"cpu_pct_{name}": value for name, value in cpu_pct.items()},
        }
    finally:
        stop_rack()  # first: a drive outliving the bridge would rightly report SYNC loss
        if bridge is not None:
            bridge.stop()
        network.disconnect()


def _print_rate(mode: str, rate_hz: int, r: JsonDict) -> None:
    if not r.get("ok"):
        print(f"\n[{mode} {rate_hz} Hz] FAILED: {r.get('error')}")
        return
    cpu = ", ".join(f"{k[8:]} {v:.0f} %" for k, v in r.items() if k.startswith("cpu_pct_"))
    print(
        f"\n[{mode} {rate_hz} Hz] {r['cycles']} cycles ({r['achieved_hz']:.1f} Hz achieved)\n"
        f"  on time (every TPDO before the next SYNC)  {100 * r['on_time_share']:.2f} %\n"
        f"  SYNC -> last TPDO  p50 {r['latency_p50_ms']:.3f} ms, p99 "
        f"{r['latency_p99_ms']:.3f} ms\n"
        f"  cycle period jitter  p50 {r['period_jitter_p50_ms']:.3f} ms, p99 "
        f"{r['period_jitter_p99_ms']:.3f} ms\n"
        f"  {r['frames_per_s']:.0f} frames/s: {r['bus_load_pct_at_1mbit']:.1f} % of a "
        f"1 Mbit/s bus with worst-case stuffing, {r['bus_load_nominal_pct_at_1mbit']:.1f} % "
        f"without\n  CPU (% of one core): {cpu}"
        + (f"\n  latched: {r['latched']}" if r["latched"] else "")
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Run every mode and rate, print the figures, end with one JSON line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="3 s per rate")
    parser.add_argument("--window-s", type=float, default=None, help="seconds per rate")
    parser.add_argument(
        "--mode", choices=(*MODES, "both"), default="both", help="default: both, in-process first"
    )
    parser.add_argument(
        "--rack-switch-interval-s",
        type=float,
        default=None,
        help="cross-process: run the rack's main() after sys.setswitchinterval(this) "
        f"(lca-can-bridge sets {GIL_SWITCH_INTERVAL_S:g}; default: the console script as is)",
    )
    args = parser.parse_args(argv)
    modes = MODES if args.mode == "both" else (args.mode,)
    window_s = args.window_s or (3.0 if args.quick else 10.0)
    sys.setswitchinterval(GIL_SWITCH_INTERVAL_S)  # as lca-can-bridge does
    warmup_s = 0.5 if args.quick else 1.0
    print(
        f"can_cycle benchmark: {window_s:g} s per rate, {os.cpu_count()} CPUs, "
        f"python {platform.python_version()}, python-can {can.__version__}, "
        f"canopen {metadata.version('canopen')}, modes {', '.join(modes)}, rack GIL switch "
        f"interval {args.rack_switch_interval_s or 'as the console script'}"
    )
    results: dict[str, dict[str, JsonDict]] = {mode: {} for mode in modes}
    for mode in modes:
        for rate_hz in RATES_HZ:
            r = run_rate(rate_hz, window_s, warmup_s, mode, args.rack_switch_interval_s)
            results[mode][str(rate_hz)] = r
            _print_rate(mode, rate_hz, r)
    targets: list[JsonDict] = []
    print()
    for (mode, rate_hz), least in TARGETS.items():
        if mode not in results:
            continue
        share = float(results[mode][str(rate_hz)].get("on_time_share", math.nan))
        met = share >= least if math.isfinite(share) else False
        targets.append({"mode": mode, "rate_hz": rate_hz, "least_on_time_share": least, "met": met})
        print(
            f"summary: {mode} {rate_hz} Hz on time {100 * share:.2f} % (target >= "
            f"{100 * least:g} %: {'MET' if met else 'NOT MET'})"
        )
    record: JsonDict = {
        "bench": "can_cycle",
        "window_s": window_s,
        "rack_switch_interval_s": args.rack_switch_interval_s,
        "targets": targets,
        "meets_targets": all(t["met"] for t in targets),
        "modes": {
            mode: {
                key: {k: (rounded(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
                for key, r in rates.items()
            }
            for mode, rates in results.items()
        },
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
    }
    print(strict_json(record, indent=None))  # strict: NaN/inf as null, with why
    return 0 if all(r.get("ok") for rates in results.values() for r in rates.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
