"""Many fault schedules under simulated time: the invariants of ``socmon chaos`` checked
on every run of :class:`agent.run.simulated.SimRuntime` (prints a report).

Each seed draws a schedule with :func:`agent.run.chaos.draw_schedule` (the kinds a simulated
run applies: kill, stop, hang), runs it in one process under simulated time (world, agent
and monitor cores, the codec, up's recorder and summary), and checks it with
:func:`agent.run.chaos.check_invariants`: recovery within its bound, fencing, the error after
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
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.run.simulated import FAULT_KINDS, SimConfig, report_lines, run_schedules  # noqa: E402
from design.gain_design import design_gains  # noqa: E402
from design.scenario import load_scenario, resolve_delays  # noqa: E402


def main(scenario: str, seeds: range, steps: int, delays_spec: str, kinds, rate: float,
         design_s: float = 0.5) -> int:
    s = load_scenario(scenario)
    delays = resolve_delays(s, delays_spec)
    t0 = time.monotonic()
    G = list(design_gains(s, delays=delays, starts=1).G)
    print(f"{s.name}: gains designed for delays {delays_spec} in {time.monotonic() - t0:.1f} s; "
          f"kinds {','.join(kinds)}, rate {rate:g}, a gain the monitor asks for comes "
          f"{design_s:g} s later")
    report = run_schedules(s, G, delays, seeds, steps, kinds, rate,
                           config=SimConfig(design_s=design_s))
    print("\n".join(report_lines(report)))
    return 1 if report["violations"] else 0


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
