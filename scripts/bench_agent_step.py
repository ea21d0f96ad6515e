"""Benchmark of one agent's own work per step, in one process (prints figures; asserts
nothing).

An agent process (agent.node.process) does, each step: decode the world's readings and
its in-neighbours' estimates, run the estimator (agent.node.core.AgentCore.poll, with the
residual tests unless ``--no-residuals``) and encode its estimate. This script does the
same with the same functions, without zenoh, on messages made beforehand, and reports
the thread CPU of each part per step:

- back to back (``--step-ms 0``): the work itself, caches warm;
- with a sleep of the step period between steps (``--step-ms 10`` ...), as a live agent
  waits for its next readings: on this machine the same work then costs several times as
  much CPU, the code and data it touches being cold again at each wake-up.

The second is what a live agent pays (scripts/bench_runtime.py measures the processes
themselves). The figures tell the work from the wake-up: an agent's CPU per step is not
brought down to the bare zenoh-python floor by doing less work alone.

Usage::

    python scripts/bench_agent_step.py [--scenario paper-14-live] [--agent 1]
        [--steps 2000] [--step-ms 0,10]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PARTS = ("decode readings", "readings", "estimates", "estimator", "encode")


def measure(scenario: str, agent: int, steps: int, step_ms: float, residuals: bool,
            gains) -> dict:
    """Thread CPU (us) of each part per step, over ``steps`` steps of agent ``agent``."""
    import numpy as np

    from agent.node.core import AgentCore, agent_config
    from agent.protocol import wire
    from broker_free_net.codec import MessageStats, try_decode
    from design.scenario import load_scenario

    sc = load_scenario(scenario)
    delays = np.zeros((sc.N, sc.N), int)
    core = AgentCore(agent_config(sc, agent, gains, seed=1, delays=delays, deadline_s=1.0,
                                  residuals=residuals))
    sources = sorted(core.role.neighbours)
    stats, senders = MessageStats(), set(core.config.agents)
    sensors_schema, est_schema = wire.sensors_schema(core.n), wire.est_schema(core.n)
    rng = np.random.default_rng(0)
    readings = [wire.encode_sensors(k, rng.standard_normal(core.n)) for k in range(steps)]
    estimates = {j: [wire.encode_est(j, k, rng.standard_normal(core.n), 0, time.time())
                     for k in range(steps)] for j in sources}
    spent = dict.fromkeys(PARTS, 0.0)
    clock, now = time.thread_time, 0.0
    for k in range(steps):
        if step_ms:
            time.sleep(step_ms / 1e3)
        t0 = clock()
        msg = try_decode(readings[k], sensors_schema, stats, now_step=max(core.step, 0),
                         window=wire.STAMP_WINDOW)
        t1 = clock()
        core.on_sensors(msg["step"], msg["x"], now=now)
        t2 = clock()
        for j in sources if k else ():
            est = try_decode(estimates[j][k - 1], est_schema, stats, senders=senders,
                             now_step=max(core.step, 0), window=wire.STAMP_WINDOW)
            core.on_estimate(est["agent"], est["step"], est["x"], now)
        t3 = clock()
        out = core.poll(now)
        t4 = clock()
        for step, x, epoch in out:
            wire.encode_est(agent, step, x, epoch, time.time())
        t5 = clock()
        for part, d in zip(PARTS, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4)):
            spent[part] += d
        now += max(step_ms, 1.0) / 1e3
    if core.step != steps - 1 or stats.total_dropped:
        raise RuntimeError(f"the agent ran to step {core.step} of {steps - 1} and dropped "
                           f"{stats.total_dropped} messages: not the work of a normal step")
    return {part: 1e6 * v / steps for part, v in spent.items()}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="paper-14-live")
    parser.add_argument("--agent", type=int, default=1)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--step-ms", default="0,10",
                        help="sleeps between steps, ms (0: back to back)")
    parser.add_argument("--no-residuals", action="store_true",
                        help="without the residual tests (a live agent runs them by default)")
    args = parser.parse_args(argv)
    from design.gain_design import design_gains
    from design.scenario import load_scenario

    try:
        sc = load_scenario(args.scenario)
    except Exception as exc:            # noqa: BLE001 - said as the flag's error
        parser.error(f"--scenario: {exc}")
    if not 1 <= args.agent <= sc.N:
        parser.error(f"--agent: {args.agent} holds no role at the start of {args.scenario} "
                     f"(agents 1..{sc.N})")
    try:
        periods = [float(x) for x in args.step_ms.split(",")]
    except ValueError:
        parser.error(f"--step-ms: comma-separated numbers of ms, got {args.step_ms!r}")
    if not all(0 <= p < 10_000 for p in periods):
        parser.error(f"--step-ms: each in [0, 10000) ms, got {args.step_ms!r}")
    if args.steps < 2:
        parser.error(f"--steps: at least 2, got {args.steps}")
    t = time.process_time()
    gains = design_gains(sc, "none", target=0.97, exact_mse=False).G
    print(f"machine: {os.cpu_count()} cores, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"{args.scenario}, agent {args.agent}: gain designed in "
          f"{time.process_time() - t:.1f} s of CPU; {args.steps} steps each; thread CPU in "
          f"us a step")
    print(f"| sleep between steps | {' | '.join(PARTS)} | total |")
    print("| --- |" + " --- |" * (len(PARTS) + 1))
    for step_ms in periods:
        us = measure(args.scenario, args.agent, args.steps, step_ms, not args.no_residuals,
                     gains)
        print(f"| {step_ms:g} ms | " + " | ".join(f"{us[p]:.1f}" for p in PARTS)
              + f" | {sum(us.values()):.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
