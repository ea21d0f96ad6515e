"""Speed of the vectorised Monte-Carlo simulator against a per-trial loop, in one run.

    python scripts/bench_simulate.py [--sampson PATH] [--trials 200] [--steps 300]

For each scenario it times ``simulate(..., trials=T)`` (all trials in one batch) and the
plain per-trial loop of the very same code, ``simulate(..., trials=1, seed=s+t)`` for
t = 0..T'-1 (T' <= T, scaled to trial-steps per second), and prints both rates and their
ratio. Scenarios: paper-14 (n N = 42) and two synthetic ones with n N = 1000
(n = 100, N = 10 and n = 50, N = 20: a random sparse A with rho(A) = 0.95, agents on a
cycle, every link delayed 2 steps, two sensors per agent). paper-14 uses the gain of
``design_gains``; the cost of a step does not depend on the gain values, so the
synthetic ones use fixed random gains that keep the run bounded. With ``--sampson`` it also times the paper's Sampson experiment: gain design
for the delay bounds 0, 5, 10, 20 and 50 trials x 300 steps for each.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

# One BLAS thread: on a small shared machine, multi-threaded BLAS on (T x n) @ (n x n)
# products spins and runs many times slower; both sides of the comparison use the same.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from design.closed_loop import closed_loop_for  # noqa: E402
from design.gain_design import design_gains  # noqa: E402
from design.scenario import load_scenario, scenario_from_dict  # noqa: E402
from design.simulate import simulate  # noqa: E402


def synthetic(n: int, N: int, seed: int = 0):
    """Random sparse A (about 4 influences per node plus self weights), rho(A) = 0.95."""
    rng = np.random.default_rng(seed)
    A = np.zeros((n, n))
    for i in range(n):
        A[i, rng.choice(n, size=4, replace=False)] = rng.uniform(0.1, 1.0, 4)
        A[i, i] = rng.uniform(0.1, 1.0)
    A *= 0.95 / np.max(np.abs(np.linalg.eigvals(A)))
    measure = [[str(1 + (2 * a) % n), str(1 + (2 * a + 1) % n)] for a in range(N)]
    return scenario_from_dict({
        "name": f"synthetic-{n}x{N}",
        "social": {"A": A.tolist(), "process_noise": 0.05},
        "agents": {"measure": measure, "measurement_noise": 0.05},
        "network": {"topology": "cycle", "self_weight": 0.5,
                    "delays": [[2 if (j == (i + 1) % N) else 0 for j in range(N)]
                               for i in range(N)]},
    })


def bounded_gain(scenario, seed=0):
    """Small random gains, halved until the exact delayed loop is stable."""
    rng = np.random.default_rng(seed)
    G = [0.3 * rng.standard_normal((scenario.n, len(m))) for m in scenario.measure]
    for _ in range(30):
        if closed_loop_for(scenario, G).spectral_radius() < 1:
            return G
        G = [0.5 * g for g in G]
    raise RuntimeError("no bounded gain found")


def rate(scenario, G, trials, steps, seed=0):
    t0 = time.perf_counter()
    res = simulate(scenario, G, steps=steps, trials=trials, seed=seed)
    dt = time.perf_counter() - t0
    assert not res.diverged
    return trials * steps / dt, dt


def loop_rate(scenario, G, trials, steps, seed=0):
    t0 = time.perf_counter()
    for t in range(trials):
        simulate(scenario, G, steps=steps, trials=1, seed=seed + t)
    dt = time.perf_counter() - t0
    return trials * steps / dt, dt


def bench(scenario, G, trials, steps, loop_trials):
    v, dv = rate(scenario, G, trials, steps)
    lp, dl = loop_rate(scenario, G, loop_trials, steps)
    print(f"{scenario.name:>20}  nN={scenario.n * scenario.N:>5}  T={trials:>4}  "
          f"vectorised {v:>10.0f} trial-steps/s ({dv:6.2f} s)   per-trial loop "
          f"{lp:>9.0f} trial-steps/s ({loop_trials} trials, {dl:6.2f} s)   speed-up {v / lp:6.1f}x",
          flush=True)
    return v / lp


def sampson(path, steps):
    from design.experiments import design_for_bound, sampson_scenario

    s = sampson_scenario(path)
    out = []
    t_design = t_sim = 0.0
    for tau in (0, 5, 10, 20):
        t0 = time.perf_counter()
        G, D, rho = design_for_bound(s, tau)
        t1 = time.perf_counter()
        res = simulate(s, G, steps=steps, trials=50, seed=0, delays=D)
        t2 = time.perf_counter()
        t_design += t1 - t0
        t_sim += t2 - t1
        out.append((tau, rho, res.mse_steady, t1 - t0, t2 - t1))
    for tau, rho, mse, td, ts in out:
        print(f"  sampson tau={tau:>2}: exact radius {rho:.4f}, steady MSE {mse:.4f}, "
              f"design {td:6.2f} s, simulation (50 trials x {steps} steps) {ts:5.2f} s")
    print(f"  sampson experiment: simulation {t_sim:.2f} s, gain design {t_design:.2f} s, "
          f"total {t_sim + t_design:.2f} s")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--loop-trials", type=int, default=10)
    parser.add_argument("--sampson", default=None, metavar="PATH")
    args = parser.parse_args(argv)
    print(f"BLAS threads: OPENBLAS_NUM_THREADS={os.environ['OPENBLAS_NUM_THREADS']}, "
          f"steps {args.steps} (n N = 1000 cases: {args.steps // 3})", flush=True)
    p14 = load_scenario("paper-14")
    G14 = design_gains(p14).G
    for T in (20, 50, args.trials):
        bench(p14, G14, T, args.steps, args.loop_trials)
    for n, N in ((100, 10), (50, 20)):
        s = synthetic(n, N)
        G = bounded_gain(s)
        bench(s, G, args.trials, args.steps // 3, max(2, args.loop_trials // 2))
    if args.sampson:
        sampson(args.sampson, args.steps)


if __name__ == "__main__":
    main()
