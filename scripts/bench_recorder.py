"""What the recorder of ``socmon up`` keeps, with and without ``--record-every``.

The recorder (``agent.run.recorder.Recorder``) is fed, in this one process and without
zenoh, the messages a run of N agents and n states publishes over K steps (the truth and
every agent's estimate each step, encoded as on the wire); it is measured as it grows:
the Python heap it holds at the end (``tracemalloc``), the process's resident memory
added (each measurement in a fresh process), and the time per message fed (tracemalloc
on: slower than in a run). ``up`` runs the same recorder in its own process.

Usage::

    python scripts/bench_recorder.py                         # communities-32's sizes
    python scripts/bench_recorder.py --agents 32 --states 68 --steps 3000 --every 1,10
"""

from __future__ import annotations

import argparse
import gc
import json
import multiprocessing
import resource
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agent.protocol import topics, wire  # noqa: E402
from agent.run.recorder import Recorder  # noqa: E402

RUN = "bench"


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2**20


def measure(agents: int, states: int, steps: int, every: int, seed: int = 0) -> dict:
    """Feed one recorder K steps of a run; its figures."""
    rng = np.random.default_rng(seed)
    truth_key = topics.truth_key(RUN)
    est_keys = [topics.est_key(RUN, a) for a in range(1, agents + 1)]
    gc.collect()
    rss0 = _rss_mb()
    tracemalloc.start()
    r = Recorder(RUN, n=states, N=agents, M=agents, record_every=every, last_step=steps)
    fed, seconds = 0, 0.0
    for k in range(steps + 1):
        x = rng.standard_normal(states)
        batch = [(truth_key, wire.encode_truth(k, x))]
        batch += [(key, wire.encode_est(a, k, x + 0.1 * rng.standard_normal(states), 0, 0.0))
                  for a, key in enumerate(est_keys, start=1)]
        t0 = time.perf_counter()
        for key, payload in batch:
            r.feed(key, payload)
        seconds += time.perf_counter() - t0
        fed += len(batch)
    held, _ = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    out = {"agents": agents, "states": states, "steps": steps, "record_every": every,
           "kept_steps": len(r.recording.truth), "heap_mb": round(held / 2**20, 1),
           "rss_added_mb": round(_rss_mb() - rss0, 1),
           "us_per_message": round(1e6 * seconds / fed, 1)}
    del r
    gc.collect()
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=32)
    p.add_argument("--states", type=int, default=68)
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--every", default="1,10", help="record_every values, comma-separated")
    p.add_argument("--json", metavar="FILE", help="also write the rows here")
    args = p.parse_args(argv)
    try:
        everies = [int(v) for v in args.every.split(",")]
    except ValueError:
        p.error(f"--every: expected integers separated by commas, got {args.every!r}")
    if min(everies) < 1 or min(args.agents, args.states, args.steps) < 1:
        p.error("--agents, --states, --steps and every --every value must be >= 1")
    # each in a fresh process: memory freed by one measurement would serve the next
    ctx = multiprocessing.get_context("spawn")
    rows = []
    for e in everies:
        with ctx.Pool(1) as pool:
            rows.append(pool.apply(measure, (args.agents, args.states, args.steps, e)))
    print("| agents | states | steps | record every | steps kept | heap held (MB) "
          "| RSS added (MB) | us per message fed |")
    print("| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(f"| {r['agents']} | {r['states']} | {r['steps']} | {r['record_every']} | "
              f"{r['kept_steps']} | {r['heap_mb']} | {r['rss_added_mb']} | "
              f"{r['us_per_message']} |")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
