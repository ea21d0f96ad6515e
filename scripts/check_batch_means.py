"""Is one run's steady-MSE standard error (``design.metrics.batch_means_se``, what ``up``
and ``watch`` print after ``±``) the spread a user would see across runs?

Simulates ``--runs`` independent runs of K steps of a scenario with its default gain
(the one ``socmon up`` designs) and prints, for each K, the standard deviation of the
runs' steady MSEs against the mean and median of their batch-means standard errors.
A calibrated estimate puts them within a few tens of percent of each other.

    python scripts/check_batch_means.py [--scenario paper-14-live] [--runs 200]
"""

from __future__ import annotations

import argparse

import numpy as np


def main(argv=None) -> int:
    from agent.run.inputs import default_design
    from design.metrics import batch_means_se, steady_mse, steady_window
    from design.scenario import load_scenario
    from design.simulate import simulate

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scenario", default="paper-14-live")
    p.add_argument("--runs", type=int, default=200)
    p.add_argument("--steps", type=int, nargs="+", default=[400, 1000, 4000])
    p.add_argument("--seed", type=int, default=1)
    args = p.parse_args(argv)
    scenario = load_scenario(args.scenario)
    G = default_design(scenario, scenario.delays).G
    print(f"{scenario.name}, default gain, {args.runs} simulated runs per length")
    print(f"{'steps':>6} {'spread of mse_steady':>22} {'mean SE':>9} {'median SE':>10} "
          f"{'ratio':>6}")
    for K in args.steps:
        res = simulate(scenario, G, steps=K, trials=args.runs, seed=args.seed)
        q = steady_window(K)
        spread = float(np.std(steady_mse(res.mse_trials), ddof=1))
        ses = [batch_means_se(row[-q:]) for row in res.mse_trials]
        ses = np.array([s for s in ses if s is not None])
        print(f"{K:>6} {spread:>22.4f} {ses.mean():>9.4f} {np.median(ses):>10.4f} "
              f"{ses.mean() / spread:>6.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
