"""A live run with and without --secure: hop latency, CPU per process, step lag.

Runs ``socmon up paper-14-live --steps K --step-ms 10`` (world, 3 agents, standby and the
monitor as processes on loopback) alternately plain and with ``--secure`` (mutual TLS and
access control on every peer), ``--repeats`` times each, and prints the medians and the
overhead of the secure mode.

Usage: python scripts/bench_secure_run.py [--steps 2000] [--repeats 2]
"""

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run(out, secure, steps, gains):
    cmd = [sys.executable, "-m", "agent.cli", "up", "paper-14-live", "--steps", str(steps),
           "--step-ms", "10", "--gains", str(gains), "--out", str(out), "--json", "--quiet"]
    if secure:
        cmd.append("--secure")
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-2000:])
    s = json.loads(p.stdout)
    hops = [h["median"] for h in s["hop_ms"].values() if h]
    agents_cpu = [v for k, v in s["cpu_s"].items() if k.startswith("agent-") and v]
    return {"hop_ms": statistics.median(hops), "cpu_ms_per_step": 1e3 * statistics.mean(
        agents_cpu) / steps, "wall_s": s["wall_s"], "drops": s["drops"],
        "steps_per_s": steps / s["wall_s"]}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    import numpy as np

    from design.gains import save_gains
    from design.scenario import load_scenario

    tmp = Path(tempfile.mkdtemp(prefix="bench-secure-run-"))
    s = load_scenario("paper-14-live")
    gains = tmp / "g.npz"
    save_gains(gains, [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure], {"method": "fixed"})
    rows = {False: [], True: []}
    for r in range(args.repeats):
        for secure in (False, True):
            rows[secure].append(run(tmp / f"{'secure' if secure else 'plain'}{r}", secure,
                                    args.steps, gains))
    print(f"paper-14-live, {args.steps} steps of 10 ms, {args.repeats} runs each, medians")
    print(f"{'mode':8} {'hop ms':>8} {'agent CPU ms/step':>18} {'steps/s':>8} {'drops':>6}")
    med = {}
    for secure, rs in rows.items():
        m = {k: statistics.median(x[k] for x in rs) for k in rs[0]}
        med[secure] = m
        print(f"{'secure' if secure else 'plain':8} {m['hop_ms']:8.2f} "
              f"{m['cpu_ms_per_step']:18.3f} {m['steps_per_s']:8.1f} {m['drops']:6.0f}")
    for k in ("hop_ms", "cpu_ms_per_step"):
        print(f"overhead {k}: {100 * (med[True][k] / med[False][k] - 1):+.0f} %")


if __name__ == "__main__":
    main()
