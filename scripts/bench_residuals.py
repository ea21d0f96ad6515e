"""Detection of sensor and agent faults by the exact residual tests, against a naive test.

    python scripts/bench_residuals.py [--scenario paper-14-live] [--gains designed|fixed]
        [--window 8] [--trials 400] [--horizon 200] [--sizes 0.5,1,2,3,5,10]
        [--noise-factors 1.5,2,3,5,10] [--ramp 100] [--agents 1,2,3]
        [--healthy-trials 1000] [--healthy-steps 10000] [--seed 0]
    python scripts/bench_residuals.py --window-sweep 1,4,8,16,32

For the scenario (default ``paper-14-live``) with gains designed by the default method
(what ``socmon up`` does) or ``fixed`` (0.5 on every measured node), it builds the
residual tests of :mod:`design.residuals` (default false-alarm rate: 0.01 expected alarm
steps per 10,000-step healthy run, all agents together) and prints:

1. **False alarms** per 10,000 healthy steps (all agents): ``--healthy-trials`` runs of
   ``--healthy-steps`` steps, alarm steps and alarm episodes (runs of consecutive alarm
   steps) of the exact test against the expected value, and those of the naive test.
2. **Detection** for every fault kind (``bias``, ``drift``, ``lie``: offsets of SIZE
   measurement-noise std-devs on every component; ``drift`` reaches SIZE after
   ``--ramp`` steps; ``lie-hidden``: a lie of the same Euclidean size along the direction
   its receivers' tests see least, see :func:`hidden_direction`; ``noise``: the sensor
   noise multiplied by the factor), size and faulty agent: the fraction of
   ``--trials`` trials detected within ``--horizon`` steps of the fault, the median and
   90th percentile delay, the share whose verdict at the first alarm
   (:func:`design.residuals.isolate`) names the right agent and kind, and the MSE excess
   while undetected (the faulty run minus the healthy run with the same seed, averaged
   over the steps from the fault to the detection, in % of the healthy steady MSE).
3. The same detection figures (``step``) for the exact covariance used without window
   and without links: one reading's innovation squared over its exact variance against
   ``chi2.isf(alpha, 1)`` per agent (the agent's whole budget), the simplest test with an
   exact threshold. And (``naive``) for the **naive test** a user would write without the
   exact covariance: an alarm when one reading's innovation exceeds 3 std-devs of the
   measurement noise alone, ``|y - H xhat_prior| > 3 sqrt(r)``, naming the agent whose
   innovation alarmed (as a sensor fault). Its delay counts its first alarm at or after
   the fault, ignoring the ones before (which its false-alarm rate shows).

With ``--window-sweep`` it only prints, for each window length, the detected share and
median delay of a few faults (100 trials each): how the default window was chosen.

Faults start ``20`` steps after the tests' warm-up; all trials of a cell share the
seed, so the faulty and healthy runs see the same noise.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from design.gain_design import design_gains  # noqa: E402
from design.residuals import (  # noqa: E402
    INCONSISTENT,
    SENSOR_BIAS,
    first_alarms,
    isolate,
    reports_at,
    residual_test,
)
from design.scenario import load_scenario  # noqa: E402
from design.simulate import Fault, simulate  # noqa: E402

NAIVE_SIGMAS = 3.0
CHUNK = 100          # trials per simulation of the healthy runs (memory)
NEVER = 10 ** 9


def hidden_direction(s, test, agent):
    """The lie direction (norm sqrt(n), as the all-ones offset) that the receivers' tests
    see least at its first use: the right singular vector of the smallest singular value
    of the stacked ``Wh (1 - w) A^age`` over the agent's receivers (``Wh`` whitening both
    the kept and the discarded directions)."""
    A = np.asarray(s.A, dtype=float)
    rows = []
    for r in test.residuals:
        if r.sender != agent:
            continue
        Wh = r.whiten if r.null_basis is None else np.vstack(
            [r.whiten, r.null_basis.T / np.sqrt(r.null_floor)])
        w = float(s.W[r.agent, agent])
        rows.append(Wh @ ((1 - w) * np.linalg.matrix_power(A, r.age)))
    _, _, Vt = np.linalg.svd(np.vstack(rows))
    return tuple(Vt[-1] * np.sqrt(s.n))


def naive_alarms(innovations, r):
    """(trials, steps+1, N) per agent: some reading's innovation beyond 3 sqrt(r)."""
    with np.errstate(invalid="ignore"):
        return np.abs(innovations) > NAIVE_SIGMAS * np.sqrt(r)


def per_step_alarms(innovations, test):
    """(trials, steps+1, N): the exact per-step innovation test without window or links,
    ``inn^2 / var > chi2.isf(alpha, 1)`` per agent with the agent's whole budget alpha
    (innovations with one reading per agent, as on paper-14-live)."""
    var = np.array([r.cov_step[0, 0] for r in test.residuals if r.sender is None])
    thr = stats.chi2.isf(test.alpha, 1)
    with np.errstate(invalid="ignore"):
        hit = innovations ** 2 / var > thr
    hit[:, :test.warmup + 1] = False
    return hit


def episodes(hit):
    """Runs of consecutive True along the step axis (axis 1), summed over everything."""
    h = hit.astype(np.int8)
    starts = np.diff(h, axis=1, prepend=0) == 1
    return int(starts.sum())


def false_alarms(s, G, test, trials, steps, seed):
    """Alarm steps and episodes per run of ``steps`` steps (all agents): exact, naive."""
    exact_steps = exact_eps = naive_steps = naive_eps = 0
    tested = naive_tested = step_steps = step_tested = 0
    done = 0
    while done < trials:
        t = min(CHUNK, trials - done)
        res = simulate(s, G, steps=steps, trials=t, seed=seed + done, residuals=test)
        with np.errstate(invalid="ignore"):
            hit = (res.residual_stats > test.thresholds).any(axis=2)
        hit[:, :test.first_step] = False
        exact_steps += int(hit.sum())
        exact_eps += episodes(hit)
        nh = naive_alarms(res.innovations, s.measurement_noise)
        nh = nh.any(axis=2)
        nh[:, 0] = False
        naive_steps += int(nh.sum())
        naive_eps += episodes(nh)
        tested += t * (steps - test.first_step + 1)
        naive_tested += t * steps
        ph = per_step_alarms(res.innovations, test).any(axis=2)
        step_steps += int(ph.sum())
        step_tested += t * (steps - test.warmup)
        done += t
    per = 10_000
    return {
        "exact_steps": exact_steps * per / tested, "exact_episodes": exact_eps * per / tested,
        "exact_expected": test.expected_false_alarms(per + test.first_step - 1),
        "exact_count": exact_steps,
        "naive_steps": naive_steps * per / naive_tested,
        "naive_episodes": naive_eps * per / naive_tested,
        "trial_steps": tested,
        "step_steps": step_steps * per / step_tested,
        "step_count": step_steps,
        "step_expected": test.alpha * test.N * per,
    }


def detection(s, G, test, fault, trials, horizon, seed, healthy):
    """Detection figures of one fault for the exact and the naive tests."""
    f = fault.start
    steps = f + horizon
    res = simulate(s, G, steps=steps, trials=trials, seed=seed, residuals=test,
                   faults=[fault])
    first = first_alarms(res.residual_stats, test.thresholds, start=f)
    when = np.where(first >= 0, first, NEVER).min(axis=1)
    early = first_alarms(res.residual_stats[:, :f], test.thresholds, start=test.first_step)
    kind = INCONSISTENT if fault.kind == "lie" else SENSOR_BIAS
    right = 0
    for t in np.nonzero(when < NEVER)[0]:
        v = isolate(reports_at(test, test.levels(res.residual_stats[t, when[t]])))
        right += v is not None and v.agent == fault.agent and v.kind == kind
    nh = naive_alarms(res.innovations, s.measurement_noise)
    nh[:, :f] = False
    nwhen = np.where(nh.any(axis=2).any(axis=1), np.argmax(nh.any(axis=2), axis=1), NEVER)
    nright = 0
    for t in np.nonzero(nwhen < NEVER)[0]:
        agents = np.nonzero(nh[t, nwhen[t]])[0]
        nright += fault.kind != "lie" and list(agents) == [fault.agent]
    ph = per_step_alarms(res.innovations, test)
    ph[:, :f] = False
    pwhen = np.where(ph.any(axis=2).any(axis=1), np.argmax(ph.any(axis=2), axis=1), NEVER)
    pright = 0
    for t in np.nonzero(pwhen < NEVER)[0]:
        pright += fault.kind != "lie" and list(np.nonzero(ph[t, pwhen[t]])[0]) == [fault.agent]
    excess = (res.mse_trials - healthy.mse_trials[:, :steps + 1]) / healthy.mse_steady
    mse_und = []
    for t in range(trials):
        end = min(when[t], steps + 1)
        mse_und.append(excess[t, f:end].mean() if end > f else 0.0)
    return {"exact": _summary(when, f, right), "naive": _summary(nwhen, f, nright),
            "step": _summary(pwhen, f, pright),
            "mse_undetected_pct": 100 * float(np.mean(mse_und)),
            "alarms_before": int((early >= 0).any(axis=1).sum())}


def _summary(when, f, right):
    det = when < NEVER
    d = when[det] - f
    return {"detected": float(det.mean()),
            "median": float(np.median(d)) if det.any() else float("nan"),
            "p90": float(np.percentile(d, 90)) if det.any() else float("nan"),
            "named": right / max(1, int(det.sum()))}


SWEEP_CELLS = (("bias", 2, 0), ("bias", 3, 0), ("bias", 5, 0), ("bias", 5, 1), ("bias", 5, 2),
               ("drift", 2, 0), ("noise", 3, 0))


def window_sweep(scenario="paper-14-live", windows=(1, 4, 8, 16, 32), trials=100, seed=1,
                 horizon=200, out=print):
    """Detected share and median delay of a few faults for each window length."""
    s = load_scenario(scenario)
    G = design_gains(s).G
    out(f"{scenario}, designed gains: detected share / median delay (steps) within "
        f"{horizon} steps, {trials} trials, default alpha; kind size/agent")
    out(f"{'window':>6} | " + " | ".join(f"{k}{x:g}/{a + 1:<2}" for k, x, a in SWEEP_CELLS))
    for W in windows:
        test = residual_test(s, G, window=W)
        f = test.first_step + 20
        row = []
        for kind, size, agent in SWEEP_CELLS:
            res = simulate(s, G, steps=f + horizon, trials=trials, seed=seed,
                           residuals=test, faults=[Fault(kind, agent, f, float(size))])
            first = first_alarms(res.residual_stats, test.thresholds, start=f)
            when = np.where(first >= 0, first, NEVER).min(axis=1)
            det = when < NEVER
            med = np.median(when[det] - f) if det.any() else float("nan")
            row.append(f"{det.mean():.2f} {med:>4.0f}")
        out(f"{W:>6} | " + " | ".join(f"{c:>9}" for c in row))


def main(scenario="paper-14-live", gains="designed", window=8, trials=400, horizon=200,
         sizes=(0.5, 1, 2, 3, 5, 10), noise_factors=(1.5, 2, 3, 5, 10), ramp=100,
         agents=None, healthy_trials=1000, healthy_steps=10_000, seed=0, out=print):
    s = load_scenario(scenario)
    t0 = time.perf_counter()
    if gains == "designed":
        G = design_gains(s).G
    else:
        G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    test = residual_test(s, G, window=window)
    agents = list(range(s.N)) if agents is None else list(agents)
    out(f"{scenario}: n = {s.n}, N = {s.N}, gains {gains} (rho {test.rho:.4f}), window "
        f"{test.window}, alpha {test.alpha:.3g} per agent per step, warm-up {test.warmup} "
        f"steps; statistics: " + ", ".join(f"{r.name} (dof {r.dof}/{r.dim}, threshold "
                                            f"{r.threshold:.1f})" for r in test.residuals))
    fa = false_alarms(s, G, test, healthy_trials, healthy_steps, seed + 10_000)
    out("")
    out(f"False alarms per 10,000 healthy steps (all agents; {fa['trial_steps']:,} tested "
        f"trial-steps, {healthy_trials} runs of {healthy_steps} steps):")
    out(f"  exact test   alarm steps {fa['exact_steps']:.4f} ({fa['exact_count']} in all), "
        f"episodes {fa['exact_episodes']:.4f}, expected alarm steps "
        f"{fa['exact_expected']:.4f}")
    out(f"  naive 3-sigma alarm steps {fa['naive_steps']:.1f}, episodes "
        f"{fa['naive_episodes']:.1f}")
    out(f"  exact per-step innovation test (no window, no links) alarm steps "
        f"{fa['step_steps']:.4f} ({fa['step_count']} in all), expected "
        f"{fa['step_expected']:.4f}")
    out("")
    out(f"Detection within {horizon} steps ({trials} trials per row; delay in steps from "
        f"the fault; named = right agent and kind at the first alarm; MSE+% = MSE excess "
        f"while undetected, in % of the healthy steady MSE):")
    head = (f"{'kind':10} {'size':>5} {'agent':>5} | {'det':>5} {'med':>5} {'p90':>5} "
            f"{'named':>6} {'MSE+%':>7} | {'step det':>8} {'med':>5} {'p90':>5} {'named':>6} "
            f"| {'naive det':>9} {'med':>5} {'p90':>5} {'named':>6}")
    out(head)
    out("-" * len(head))
    healthy = {}
    cells = [("bias", x) for x in sizes] + [("drift", x) for x in sizes] + \
        [("lie", x) for x in sizes] + [("lie-hidden", x) for x in sizes] + \
        [("noise", x) for x in noise_factors]
    f = test.first_step + 20
    for kind, size in cells:
        for a in agents:
            key = f + horizon
            if key not in healthy:
                healthy[key] = simulate(s, G, steps=key, trials=trials, seed=seed)
            if kind == "lie-hidden":
                fault = Fault("lie", a, f, float(size), direction=hidden_direction(s, test, a))
            else:
                fault = Fault(kind, a, f, float(size), ramp=ramp)
            r = detection(s, G, test, fault, trials, horizon, seed, healthy[key])
            e, nv, ps = r["exact"], r["naive"], r["step"]
            out(f"{kind:10} {size:>5g} {a + 1:>5} | {e['detected']:>5.2f} {e['median']:>5.0f} "
                f"{e['p90']:>5.0f} {e['named']:>6.2f} {r['mse_undetected_pct']:>7.1f} | "
                f"{ps['detected']:>8.2f} {ps['median']:>5.0f} {ps['p90']:>5.0f} "
                f"{ps['named']:>6.2f} | "
                f"{nv['detected']:>9.2f} {nv['median']:>5.0f} {nv['p90']:>5.0f} "
                f"{nv['named']:>6.2f}")
    out("")
    out(f"({time.perf_counter() - t0:.0f} s)")


def _floats(text):
    return tuple(float(x) for x in text.split(",") if x)


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scenario", default="paper-14-live")
    p.add_argument("--gains", choices=("designed", "fixed"), default="designed")
    p.add_argument("--window", type=int, default=8)
    p.add_argument("--trials", type=int, default=400)
    p.add_argument("--horizon", type=int, default=200)
    p.add_argument("--sizes", type=_floats, default=(0.5, 1, 2, 3, 5, 10))
    p.add_argument("--noise-factors", type=_floats, default=(1.5, 2, 3, 5, 10))
    p.add_argument("--ramp", type=int, default=100)
    p.add_argument("--agents", type=lambda t: tuple(int(x) - 1 for x in t.split(",")),
                   default=None, help="1-based agent ids to corrupt (default: all)")
    p.add_argument("--healthy-trials", type=int, default=1000)
    p.add_argument("--healthy-steps", type=int, default=10_000)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--window-sweep", type=lambda t: tuple(int(x) for x in t.split(",")),
                   default=None, help="only compare these window lengths (e.g. 1,4,8,16,32)")
    a = p.parse_args()
    if a.window_sweep:
        window_sweep(a.scenario, a.window_sweep, trials=min(a.trials, 100), seed=a.seed + 1,
                     horizon=a.horizon)
        sys.exit(0)
    main(a.scenario, a.gains, a.window, a.trials, a.horizon, a.sizes, a.noise_factors,
         a.ramp, a.agents, a.healthy_trials, a.healthy_steps, a.seed)
