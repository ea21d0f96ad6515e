"""A real partition measured: a host's link brought down on a testbed of namespaces.

Runs ``socmon up SCENARIO --netns --fault linkdown:STEP:AGENT:SECONDS`` repeatedly (every
process on its own network namespace host, agent AGENT's bridge port down for SECONDS) and
reads each run's summary (its failures come from the monitor's ``events.jsonl``):

- detection: the monitor's verdict time minus the time ``up`` brought the link down;
- activation: steps from the link going down to the first reassignment's ``activate_at``,
  times the step period (the nominal time the replacement's role begins);
- confirmed: from the link going down to the monitor's record that every agent confirmed
  (absent when confirmed within the tick of the reassignment); ``epochs``: the last epoch
  (above 1 when ``activate_at`` passed before every agent confirmed and the monitor
  re-issued the roles);
- fenced: from the link coming back to the first status of the cut-off agent saying it
  dropped its role (resolution: the status period, 0.2 s);
- rejected: estimates of the old agent that receivers dropped as fenced meanwhile.

Usage (root): python scripts/bench_netns.py [--repeats 3] [--seconds 2] [--steps 400]
[--out DIR]
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENARIO = "paper-14-live"
STEP_MS = 20.0


def one_run(out, step, agent, seconds, steps):
    cmd = [sys.executable, "-m", "agent.cli", "up", SCENARIO, "--steps", str(steps),
           "--step-ms", str(STEP_MS), "--out", str(out), "--json", "--quiet", "--netns",
           "--fault", f"linkdown:{step}:{agent}:{seconds}"]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {p.returncode}: {p.stderr[-2000:]}")
    s = json.loads(p.stdout)
    down = next(e for e in s["events"] if e.get("link") == "down")
    failures = [f for f in s["failures"] if f["agent"] == agent]
    if not failures:
        return {"convicted": False}
    f = failures[0]
    records = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    confirmed = next((r for r in records if r.get("kind") == "confirmed"), None)
    up = next(e for e in s["events"] if e.get("link") == "up")
    return {"convicted": True, "cause": f["cause"], "detection_ms": f["detection_ms"],
            "activation_ms": (f["activate_at"] - down["step"]) * STEP_MS,
            "confirmed_ms": 1e3 * (confirmed["t"] - down["t"]) if confirmed else None,
            "link_up_ms": 1e3 * (up["t"] - down["t"]),
            "fenced_ms": f.get("fenced_ms"), "rejected": s["fenced"],
            "recovered": s["recovered"], "epochs": s["rosters"][-1]["epoch"],
            "other_failures": len(s["failures"]) - 1}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=2.0, help="link down for (default 2)")
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--out", help="keep the run folders here (default: a temporary folder)")
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    from agent.testbed.netns import unavailable_reason

    why = unavailable_reason()
    if why is not None:
        print(f"bench_netns: {why}", file=sys.stderr)
        return 2
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.out) if args.out else Path(tmp)
        for i in range(args.repeats):
            r = one_run(folder / f"run{i}", 100, 2, args.seconds, args.steps)
            rows.append(r)
            print(f"run {i}: " + ", ".join(
                f"{k} {v:.0f}" if isinstance(v, float) else f"{k} {v}" for k, v in r.items()),
                flush=True)
    print(f"\n{SCENARIO}, {STEP_MS:g} ms steps, agent 2's link down {args.seconds:g} s at "
          f"step 100, {args.repeats} runs (lease 1 s, hang timeout 1 s):")
    for key in ("detection_ms", "activation_ms", "confirmed_ms", "link_up_ms", "fenced_ms"):
        vals = [r[key] for r in rows if r.get(key) is not None]
        if vals:
            print(f"  {key:14s} median {statistics.median(vals):7.0f}  min {min(vals):7.0f}  "
                  f"max {max(vals):7.0f}  (n={len(vals)})")
    print(f"  convicted {sum(r['convicted'] for r in rows)}/{len(rows)}, recovered "
          f"{sum(bool(r.get('recovered')) for r in rows)}/{len(rows)}, causes "
          f"{sorted({r.get('cause') for r in rows if r['convicted']})}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
