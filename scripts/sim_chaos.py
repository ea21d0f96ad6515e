"""Many fault schedules under simulated time: the invariants of ``socmon chaos`` checked
on every run of :class:`agent.sim_runtime.SimRuntime` (prints a report).

Each seed draws a schedule with :func:`agent.chaos.draw_schedule` (the kinds a simulated
run applies: kill, stop, hang), runs it in one process under simulated time (world, agent
and monitor cores, the codec, up's recorder and summary), and checks it with
:func:`agent.chaos.check_invariants`: recovery within its bound, fencing, the error after
each switch, and convictions (only faulted agents, every dead agent that held a role).

Usage::

    python scripts/sim_chaos.py [--scenario paper-14-live] [--seeds 0:1000] [--steps 1500]
        [--delays scenario|none|uniform:T] [--kinds kill,stop,hang] [--rate 3]
        [--design-s 0.5]

Exit status 1 if any run broke an invariant (each is listed with its seed).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.chaos import draw_schedule  # noqa: E402
from agent.sim_runtime import FAULT_KINDS, SimConfig, SimRuntime  # noqa: E402
from design.gain_design import design_gains  # noqa: E402
from design.scenario import load_scenario, resolve_delays  # noqa: E402


def main(scenario: str, seeds: range, steps: int, delays_spec: str, kinds, rate: float,
         design_s: float = 0.5) -> int:
    s = load_scenario(scenario)
    delays = resolve_delays(s, delays_spec)
    t0 = time.monotonic()
    G = list(design_gains(s, delays=delays, starts=1).G)
    print(f"{s.name}: gains designed for delays {delays_spec} in {time.monotonic() - t0:.1f} s; "
          f"{len(seeds)} schedules of {steps} steps, kinds {','.join(kinds)}, rate {rate:g}, "
          f"a gain the monitor asks for comes {design_s:g} s later")
    faults, broken, convicted = Counter(), [], Counter()
    detection = {k: [] for k in ("kill", "hang", "stop")}
    switch, runs_s = [], []
    for seed in seeds:
        schedule = draw_schedule(s, seed, steps, kinds=kinds, rate=rate)
        t = time.monotonic()
        result = SimRuntime(s, G, delays, seed=seed, faults=schedule,
                            config=SimConfig(design_s=design_s)).run(steps)
        runs_s.append(time.monotonic() - t)
        faults.update(f.kind for f in schedule)
        for v in result.violations():
            broken.append((seed, v))
        for f in result.summary.get("failures", []):
            convicted[f.get("cause")] += 1
            if f.get("detected_step") is None:
                continue
            fault = max((g for g in schedule if g.agent == f["agent"]
                         and g.step <= f["detected_step"] + 5), key=lambda g: g.step,
                        default=None)
            if fault is not None and fault.kind in detection:
                detection[fault.kind].append(f["detected_step"] - fault.step)
            if f.get("activate_at") is not None:
                switch.append(f["activate_at"] - f["detected_step"])
    print(f"runs: {len(runs_s)}, {np.sum(runs_s):.1f} s of CPU ({np.median(runs_s):.2f} s median"
          f" a run, {max(runs_s):.2f} s at most, gain designs included)")
    print(f"faults injected: {dict(faults)}; verdicts: {dict(convicted)}")
    for kind, d in detection.items():
        if d:
            print(f"  {kind}: detected {np.median(d):.0f} steps after the fault (median), "
                  f"{min(d)} to {max(d)}")
    if switch:
        print(f"  roles in force {np.median(switch):.0f} steps after the verdict (median), "
              f"{min(switch)} to {max(switch)}")
    by = Counter(v.invariant for _, v in broken)
    print(f"violations: {len(broken)} in {len({seed for seed, _ in broken})} runs "
          f"{dict(by) if by else ''}")
    for seed, v in broken[:30]:
        print(f"  seed {seed}: {v.invariant} at step {v.step}: {v.evidence}")
    return 1 if broken else 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="paper-14-live")
    parser.add_argument("--seeds", default="0:200", help="A:B, the seeds A..B-1")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--delays", default="scenario", help="scenario, none or uniform:T")
    parser.add_argument("--kinds", default="kill,stop,hang",
                        help=f"comma-separated, among {','.join(FAULT_KINDS)}")
    parser.add_argument("--rate", type=float, default=3.0, help="faults per 1000 steps")
    parser.add_argument("--design-s", type=float, default=0.5,
                        help="simulated time a gain the monitor asks for takes to come")
    args = parser.parse_args()
    a, b = (int(x) for x in args.seeds.split(":"))
    kinds = tuple(k for k in args.kinds.split(",") if k)
    if not set(kinds) <= set(FAULT_KINDS):
        parser.error(f"--kinds: among {FAULT_KINDS}, got {kinds}")
    sys.exit(main(args.scenario, range(a, b), args.steps, args.delays, kinds, args.rate,
                  args.design_s))
