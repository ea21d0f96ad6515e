"""Benchmark: the paper's CCL/LMI baseline against the default gain design.

Every case runs in its own subprocess (separate peak memory, a hard time cap); the
parent prints one table. Peak memory is the child's ``ru_maxrss`` (whole process,
interpreter and libraries included). A case that exceeds the cap is stopped and
reported as such; once a method has been stopped on a random scenario, the larger
random scenarios are not run for it (they are larger still).

Usage (from the project root)::

    python scripts/bench_design.py [--cap SECONDS] [--json FILE] [--only NAMES]

Cases: paper-14 delay-free and uniform:7; Sampson-like (18 nodes, rho(A) = 1.1, 4 agents
measuring 1, 5, 12, 18 on a directed cycle, Q = R = 0.1, delay-free); random scenarios
with n*N = 100, 300, 1000 (delay-free). Methods: ``ccl`` with CLARABEL (the paper's
stop rule, the default solver), ``ccl`` with SCS, ``default`` (objective rho, default options,
60 s optimisation budget) and ``default`` stopped as soon as it reaches the radius of
the CLARABEL baseline (or of the SCS one when CLARABEL did not finish): the time to
equal rho; where no baseline gave a stable radius, stopped at rho < 0.999 (the time to
a first stabilising gain).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SAMPSON = ROOT.parent.parent / "shared" / "data" / "sampson" / "sampson_samplike_edges.csv"
if not SAMPSON.is_file():
    SAMPSON = ROOT.parent / "shared" / "data" / "sampson" / "sampson_samplike_edges.csv"

CASES = {
    "paper-14": ("paper-14", "none"),
    "paper-14 uniform:7": ("paper-14", "uniform:7"),
    "sampson": ("sampson", "none"),
    "random nN=100": ("random:25x4", "none"),
    "random nN=300": ("random:50x6", "none"),
    "random nN=1000": ("random:100x10", "none"),
}
MEMORY_GB = 8.0                # default address-space cap of a child (GiB)


def random_scenario(n: int, N: int, p: int = 2, rho: float = 1.1, degree: float = 3.0,
                    seed: int = 0):
    """A random strongly connected social graph (a Hamiltonian cycle plus ~``degree``
    random in-links per node, self weights), rho(A) = ``rho``; ``N`` agents on a directed
    cycle, each measuring ``p`` distinct random nodes; Q = R = 0.1."""
    import numpy as np

    from design.scenario import scenario_from_dict

    rng = np.random.default_rng(seed)
    mask = rng.random((n, n)) < degree / n
    perm = rng.permutation(n)
    mask[perm, np.roll(perm, 1)] = True
    np.fill_diagonal(mask, True)
    A = np.where(mask, rng.uniform(0.1, 1.0, (n, n)), 0.0)
    A *= rho / np.max(np.abs(np.linalg.eigvals(A)))
    nodes = rng.choice(n, size=N * p, replace=False)
    measure = [[str(int(v) + 1) for v in nodes[i * p:(i + 1) * p]] for i in range(N)]
    return scenario_from_dict({
        "name": f"random-n{n}-N{N}",
        "social": {"A": A.tolist(), "process_noise": 0.1},
        "agents": {"measure": measure, "measurement_noise": 0.1},
        "network": {"topology": "cycle", "self_weight": 0.5},
    }, source=f"random:{n}x{N}")


def load(spec):
    from design.scenario import load_scenario

    if spec == "sampson":
        from design.experiments import sampson_scenario

        return sampson_scenario(SAMPSON)
    if spec.startswith("random:"):
        n, N = (int(x) for x in spec.split(":", 1)[1].split("x"))
        return random_scenario(n, N)
    return load_scenario(spec)


def child(case: str, method: str, target: float | None, memory_gb: float) -> None:
    """Run one case and print one JSON line."""
    limit = int(memory_gb * 2**30)
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    sys.path.insert(0, str(ROOT))
    from design.closed_loop import ClosedLoop
    from design.gain_design import design_gains

    spec, delays = CASES[case]
    s = load(spec)
    opts = {}
    if method == "ccl-clarabel":
        kw = dict(method="ccl", solver="CLARABEL")
    elif method == "ccl-scs":
        kw = dict(method="ccl", solver="SCS")
    elif method == "default":
        kw = dict(method="default")
    else:
        kw = dict(method="default")
        opts = {"target": target}      # default@baseline-rho, default@stabilise
    t0 = time.perf_counter()
    res = design_gains(s, delays=delays, **kw, **opts)
    seconds = time.perf_counter() - t0
    rho = ClosedLoop(s.A, s.W, res.delays, s.measure, res.G).spectral_radius()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    print(json.dumps({"case": case, "method": method, "n": s.n, "N": s.N,
                      "params": s.n * sum(len(m) for m in s.measure), "seconds": seconds,
                      "rho": rho, "stable": bool(rho < 1), "iterations": res.iterations,
                      "status": res.status, "rho_delay_free": res.rho_delay_free,
                      "peak_mb": peak}))


def run_case(case, method, cap, target=None, memory_gb=MEMORY_GB):
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", case, method,
           "--memory-gb", repr(memory_gb)]
    if target is not None:
        cmd += ["--target", repr(target)]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=cap, env=env,
                             cwd=str(ROOT))
    except subprocess.TimeoutExpired:
        return {"case": case, "method": method, "stopped": f"stopped after {cap:.0f} s",
                "seconds": time.perf_counter() - t0}
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        tail = (out.stderr.strip().splitlines() or ["?"])[-1]
        if "memory allocation" in tail or "MemoryError" in tail:
            tail = f"out of memory under the {memory_gb:g} GiB cap ({tail[:80]})"
        return {"case": case, "method": method, "failed": tail[:160],
                "seconds": time.perf_counter() - t0}
    return json.loads(lines[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cap", type=float, default=600.0, help="seconds per case (default 600)")
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--only", default=None, help="comma-separated case names")
    ap.add_argument("--methods", default="ccl-clarabel,ccl-scs,default,default@baseline-rho",
                    help="comma-separated methods to run (default: all four)")
    ap.add_argument("--memory-gb", type=float, default=MEMORY_GB,
                    help=f"address-space cap per case in GiB (default {MEMORY_GB:g})")
    ap.add_argument("--child", nargs=2, metavar=("CASE", "METHOD"), help=argparse.SUPPRESS)
    ap.add_argument("--target", type=float, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        child(args.child[0], args.child[1], args.target, args.memory_gb)
        return 0
    cases = list(CASES) if not args.only else [c.strip() for c in args.only.split(",")]
    rows, stopped_random = [], set()
    methods = [m.strip() for m in args.methods.split(",")]
    print(f"# bench_design: cap {args.cap:.0f} s and {args.memory_gb:g} GiB per case, "
          f"{os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}", flush=True)
    for case in cases:
        base = {}
        for method in methods:
            if method == "default@baseline-rho":
                ref = base.get("ccl-clarabel") or base.get("ccl-scs")
                if ref is None or ref["rho"] >= 1:
                    # no stable baseline radius to match: time to the first stabilising gain
                    method, target = "default@stabilise", 0.999
                else:
                    target = ref["rho"]
                row = run_case(case, method, args.cap, target=target, memory_gb=args.memory_gb)
                row["target"] = target
            elif case.startswith("random") and method in stopped_random:
                row = {"case": case, "method": method,
                       "stopped": "not run: a smaller random case already hit the cap"}
            else:
                row = run_case(case, method, args.cap, memory_gb=args.memory_gb)
            if "rho" in row and method.startswith("ccl"):
                base[method] = row
            if case.startswith("random") and ("stopped" in row or "failed" in row):
                stopped_random.add(method)
            rows.append(row)
            print(_format(row), flush=True)
    print()
    print(_table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


def _format(row) -> str:
    if "rho" in row:
        return (f"{row['case']:<20} {row['method']:<22} {row['seconds']:9.2f} s  "
                f"rho {row['rho']:.4f}  peak {row['peak_mb']:7.0f} MB  ({row['status']})")
    return f"{row['case']:<20} {row['method']:<22} {row.get('stopped') or row.get('failed')}"


def _table(rows) -> str:
    out = ["| case | method | seconds | rho (exact) | stable | peak MB | note |",
           "| --- | --- | ---: | ---: | --- | ---: | --- |"]
    for r in rows:
        if "rho" in r:
            note = r["status"] + (f"; target {r['target']:.4f}" if "target" in r else "")
            out.append(f"| {r['case']} | {r['method']} | {r['seconds']:.2f} | {r['rho']:.4f} | "
                       f"{'yes' if r['stable'] else 'NO'} | {r['peak_mb']:.0f} | {note} |")
        else:
            out.append(f"| {r['case']} | {r['method']} | - | - | - | - | "
                       f"{r.get('stopped') or r.get('failed')} |")
    return "\n".join(out)


if __name__ == "__main__":
    sys.exit(main())
