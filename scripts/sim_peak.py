"""The error peak of a recovery, averaged over many runs under simulated time (prints a table).

One live run cannot tell a recovery's transient from the noise: a healthy run's largest
step is several times its exact level. This script runs the whole runtime
(:class:`agent.run.simulated.SimRuntime`: world, agents, standby, two monitors, the codec,
``up``'s recorder and summary; the monitor's own verdicts, reassignments, gain requests and
continuity at the switch) ``--runs`` times per case, each with its own noise seed, and
averages the per-step MSE over the runs. For each delay bound T (``--delays uniform:T``,
the run's gain designed for it as ``socmon up`` designs it: least steady MSE,
:func:`agent.run.inputs.gains_for`; ``--initial-gain rho`` takes the gain of least
radius instead, as this script did before, whose own level is 1.6-2.9x the refined level
after recovery) and each case (every single agent of the initial
configuration crashed at ``--fail-step``, agents 1 and 2 together, and no fault), it
prints:

- the exact steady MSE of the configuration in force at the end (``after``);
- the peak of the averaged MSE from the fault on, over ``after`` (the target: <= 3x);
- the steps from the fault on where the averaged MSE is above 2x ``after``;
- the averaged MSE over the 50 steps before the fault, over the exact level then;
- the steps from the fault to the roles in force (median over the runs), the first gain
  put in force (``polished``, ``fast`` or ``refined``, the most frequent over the runs)
  and the runs reported recovered.

Usage::

    python scripts/sim_peak.py [--scenario paper-14-live] [--taus 3,7,15] [--runs 50]
        [--steps 400] [--fail-step 150] [--design-s 0.5] [--initial-gain mse|rho]
        [--gains-cache DIR] [--no-precompute]

``--no-precompute``: as ``socmon up --no-precompute``, the monitors design nothing ahead;
each failure's first gain is the fast design from the gains in force (the carried gains
when their eigenvalues are counted below 0.975, :func:`design.gain_design.counted_bound`),
requested when the failure comes and answered ``--design-s`` later.
"""

from __future__ import annotations

import argparse
import collections
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.run.inputs import gains_for  # noqa: E402
from agent.run.local import Fault  # noqa: E402
from agent.run.summary import predicted_mse  # noqa: E402
from agent.run.simulated import SimConfig, SimRuntime  # noqa: E402
from design.gain_design import design_gains  # noqa: E402
from design.scenario import load_scenario, resolve_delays  # noqa: E402


def peak_case(s, G, delays, killed, runs: int, steps: int, fail_step: int,
              config: SimConfig) -> dict:
    """``runs`` simulated runs of one case; the averaged MSE and what it says."""
    faults = [Fault(fail_step, "crash", a) for a in killed]
    curves, switch, recovered, after, first = [], [], 0, [], collections.Counter()
    for seed in range(runs):
        r = SimRuntime(s, G, delays, seed=seed, faults=faults, config=config).run(steps)
        mse = np.full(steps + 1, np.nan)
        mse[np.asarray(r.steps, dtype=int)] = r.mse
        curves.append(mse)
        sm = r.summary
        after.append(sm["mse_steady_exact_in_force"])
        recovered += bool(sm.get("recovered"))
        for f in sm.get("failures", []):
            if f.get("activate_at") is not None:
                switch.append(f["activate_at"] - fail_step)
        for m in r.monitors.values():
            core = getattr(m, "core", None) or m[0]
            for h in core.history[:1]:
                first["polished" if h.get("gains_polished") else h.get("gains")] += 1
    mean = np.nanmean(np.vstack(curves), axis=0)
    level = float(np.median(after))
    tail = mean[fail_step:]
    _, before = predicted_mse(s, G, delays)
    return {"after": level, "peak": float(np.nanmax(tail) / level),
            "peak_step": int(fail_step + np.nanargmax(tail)),
            "above_2x": int(np.sum(tail > 2 * level)),
            "before": float(np.nanmean(mean[fail_step - 50:fail_step]) / before),
            "switch": float(np.median(switch)) if switch else None,
            "first": first.most_common(1)[0][0] if first else "-",
            "recovered": recovered}


def initial_gain(s, delays, tau: int, objective: str, cache) -> list:
    """The run's gain for ``uniform:tau``: ``up``'s (least MSE) or the least radius one;
    kept in ``cache`` (a folder) when given: the MSE design takes minutes at T = 15."""
    path = None if cache is None else Path(cache) / f"{s.name}-uniform{tau}-{objective}.npz"
    if path is not None and path.exists():
        with np.load(path) as z:
            return [z[f"G{i}"] for i in range(len(z.files))]
    if objective == "mse":
        G = list(gains_for(s, None, delays))
    else:
        G = initial_gain(s, delays, tau, objective, cache)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, **{f"G{i}": g for i, g in enumerate(G)})
    return G


def main(scenario: str, taus, runs: int, steps: int, fail_step: int, design_s: float,
         objective: str = "mse", cache=None, precompute: bool = True) -> int:
    s = load_scenario(scenario)
    config = SimConfig(design_s=design_s, precompute=precompute)
    cases = [(a,) for a in range(1, s.N + 1)] + [(1, 2), ()]
    print(f"{s.name}: {runs} runs a case, {steps} steps, crash at step {fail_step}; the MSE "
          "averaged over the runs, against the exact level of the configuration in force; "
          f"the run's gain: least {'steady MSE' if objective == 'mse' else 'radius'}"
          + ("" if precompute else f"; nothing precomputed, a first gain {design_s:g} s "
             "after it is asked for"))
    print(f"{'T':>3} {'killed':>7} {'after':>8} {'peak/after':>10} {'at':>5} {'>2x':>4} "
          f"{'before/exact':>12} {'switch':>6} {'first gain':>10} {'recovered':>9} "
          f"{'cpu s':>6}", flush=True)
    for tau in taus:
        delays = resolve_delays(s, f"uniform:{tau}")
        G = initial_gain(s, delays, tau, objective, cache)
        for killed in cases:
            t = time.process_time()
            row = peak_case(s, G, delays, killed, runs, steps, fail_step, config)
            name = ",".join(map(str, killed)) or "none"
            switch = "-" if row["switch"] is None else f"{row['switch']:.0f}"
            print(f"{tau:3} {name:>7} {row['after']:8.4g} {row['peak']:10.2f} "
                  f"{row['peak_step']:5} {row['above_2x']:4} {row['before']:12.2f} "
                  f"{switch:>6} {row['first']:>10} {row['recovered']:>5}/{runs:<3} "
                  f"{time.process_time() - t:6.0f}", flush=True)
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="paper-14-live")
    parser.add_argument("--taus", default="3,7,15", help="delay bounds, comma-separated")
    parser.add_argument("--runs", type=int, default=50, help="runs (noise seeds) a case")
    parser.add_argument("--steps", type=int, default=400)
    parser.add_argument("--fail-step", type=int, default=150)
    parser.add_argument("--design-s", type=float, default=0.5,
                        help="simulated time a gain the monitor asks for takes to come")
    parser.add_argument("--initial-gain", choices=("mse", "rho"), default="mse",
                        help="the run's gain: least steady MSE (as socmon up, default) or "
                             "least radius")
    parser.add_argument("--gains-cache", default=None,
                        help="folder keeping the run's gain per delay bound across calls")
    parser.add_argument("--no-precompute", action="store_true",
                        help="the monitors design nothing ahead (as up --no-precompute)")
    args = parser.parse_args()
    if not 50 <= args.fail_step < args.steps:
        parser.error("--fail-step: at least 50 (the level before it) and below --steps")
    taus = [int(t) for t in args.taus.split(",") if t]
    sys.exit(main(args.scenario, taus, args.runs, args.steps, args.fail_step, args.design_s,
                  args.initial_gain, args.gains_cache, not args.no_precompute))
