"""``socmon up SCENARIO``: a whole live run on this machine, recorded into a run folder."""

from __future__ import annotations

HELP = "run world + one process per agent on this machine, record, and write a run folder"

#: --check-simulator passes when the estimates agree to this (relative, see docs/runtime.md)
CHECK_TOL = 1e-9


def add_arguments(parser) -> None:
    from ._common import add_scenario_argument

    add_scenario_argument(parser)
    parser.add_argument("--steps", type=int, default=200, help="steps to run (default 200)")
    parser.add_argument("--gains", help="gains file (.npz); default: design with the default method")
    parser.add_argument("--seed", type=int, default=0, help="run seed (default 0)")
    parser.add_argument("--out", help="run folder (default runs/<scenario>-<time>)")
    parser.add_argument("--check-simulator", action="store_true",
                        help="compare with design.simulate (same seed); exit 1 if they differ")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--delays", default="scenario",
                        help="link delays injected at start: scenario, none or uniform:T")
    parser.add_argument("--step-ms", type=float, default=None,
                        help="period of one step (default: the scenario's step_ms)")
    parser.add_argument("--deadline-ms", type=float, default=None,
                        help="agents' wait for late estimates (default: one step; "
                             "30000 with --check-simulator, so that nothing is dropped)")
    parser.add_argument("--start-timeout", type=float, default=60.0,
                        help="seconds allowed for every process to be up (default 60)")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")


def run(args) -> int:
    from ._common import run_command

    return run_command(lambda: _up(args))


class RunFailed(Exception):
    pass


def _up(args) -> int:
    import json
    import os
    import random
    import signal
    import sys
    import time
    from pathlib import Path

    import numpy as np

    from broker_free_net import keys
    from broker_free_net.codec import MessageStats, try_decode
    from broker_free_net.config import NetConfig
    from broker_free_net.peer import Peer
    from design.errors import ScenarioError
    from design.gains import gains_meta, save_gains
    from design.scenario import resolve_delays

    from .. import wire
    from ..launcher import Children, free_port
    from ._common import CommandError, check_run_flags, load_scenario_arg, to_jsonable
    from .agent_cmd import gains_for

    scenario = load_scenario_arg(args.scenario)
    if args.steps < 1:
        raise CommandError(f"--steps: must be >= 1, got {args.steps}")
    check_run_flags(args)
    try:
        delays = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise CommandError(str(exc)) from None
    step_ms = args.step_ms if args.step_ms is not None else scenario.step_ms
    if not step_ms > 0:
        raise CommandError(f"--step-ms: must be > 0, got {step_ms}")
    deadline_ms = args.deadline_ms if args.deadline_ms is not None else (
        30000.0 if args.check_simulator else step_ms)
    if not deadline_ms > 0:
        raise CommandError(f"--deadline-ms: must be > 0, got {deadline_ms}")
    quiet = args.quiet

    def say(text):
        if not quiet:
            print(f"up: {text}", file=sys.stderr, flush=True)

    if args.gains:
        G = gains_for(scenario, args.gains, delays)
        method = "file"
    else:
        say("designing gains with the default method ...")
        G = gains_for(scenario, None, delays)
        method = "default"
    out = Path(args.out) if args.out else Path("runs") / (
        f"{scenario.name}-{time.strftime('%Y%m%d-%H%M%S')}-s{args.seed}")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CommandError(f"--out: cannot make the run folder {str(out)!r}: {exc.strerror}") \
            from None
    gains_path = (out / "gains.npz").resolve()
    from design.closed_loop import closed_loop_for

    loop = closed_loop_for(scenario, G, delays)
    rho = loop.spectral_radius()
    save_gains(gains_path, G, gains_meta(scenario, method, delays, rho))
    scen_arg = str(Path(args.scenario).resolve()) if Path(args.scenario).is_file() \
        else args.scenario

    K, N, M = args.steps, scenario.N, scenario.N + scenario.standby
    run_id = f"up{os.getpid()}x{random.randrange(10**6)}"
    ports = [free_port() for _ in range(M + 2)]
    ep = [f"tcp/127.0.0.1:{p}" for p in ports]
    children = Children(out / "logs")
    truth, est, status = {}, {a: {} for a in range(1, M + 1)}, {}
    stats = MessageStats()
    est_schema, truth_schema = wire.est_schema(scenario.n), wire.truth_schema(scenario.n)
    failure = None
    interrupted = False

    def on_term(*_):
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_term)
    # Ctrl-C must stop the run even when SIGINT was inherited as ignored (a background job
    # of a non-interactive shell starts that way, and Python keeps an inherited SIG_IGN)
    old_int = signal.signal(signal.SIGINT, signal.default_int_handler)
    t_begin = time.monotonic()
    try:
        with Peer(NetConfig(run=run_id, listen=(ep[0],)), "recorder", 0) as peer:
            truth_in = peer.subscribe(keys.truth_key(run_id), maxlen=1 << 16)
            est_in = peer.subscribe(keys.any_agent_pattern(run_id, "est"), maxlen=1 << 16)
            status_in = peer.subscribe(keys.any_agent_pattern(run_id, "status"))
            common = ["--run", run_id, "--connect", ep[0], "--seed", str(args.seed)]
            children.start("world", ["world", scen_arg, *common, "--listen", ep[1],
                                     "--steps", str(K), "--step-ms", str(step_ms),
                                     "--start-timeout", str(args.start_timeout)])
            for a in range(1, M + 1):
                argv = ["agent", scen_arg, "--id", str(a), *common, "--listen", ep[a + 1],
                        "--connect", ep[1], "--delays", args.delays,
                        "--deadline-ms", str(deadline_ms)]
                if a <= N:
                    argv += ["--gains", str(gains_path)]
                children.start(f"agent-{a}", argv)
            say(f"run {run_id}: world + {N} agents + {scenario.standby} standby started; "
                f"waiting for all to be ready (clock starts then), {K} steps of {step_ms:g} ms")

            def drain():
                for item in truth_in.drain():
                    m = try_decode(item.payload, truth_schema, stats)
                    if m is not None:
                        truth[m["step"]] = np.array(m["x"])
                for item in est_in.drain():
                    m = try_decode(item.payload, est_schema, stats, senders=set(est))
                    if m is not None:
                        est[m["agent"]][m["step"]] = np.array(m["x"])
                for item in status_in.drain():
                    m = try_decode(item.payload, wire.STATUS_SCHEMA, stats)
                    if m is not None:
                        status[m["agent"]] = m

            world_end = None
            next_progress = time.monotonic() + 1.0
            start_deadline = time.monotonic() + args.start_timeout + 30.0
            while True:
                peer.wait(timeout=0.2)
                drain()
                for child in children.reap():
                    if child.name == "world" and child.returncode == 0:
                        world_end = time.monotonic()
                    elif world_end is None:
                        raise RunFailed(f"{child.name} exited with status {child.returncode} "
                                        f"before the end of the run; its log ends:\n"
                                        f"{children.tail(child.name)}")
                now = time.monotonic()
                if not truth and now > start_deadline:
                    raise RunFailed(f"the clock did not start within {args.start_timeout:g} s; "
                                    f"world log:\n{children.tail('world')}")
                active = [a for a in range(1, M + 1)
                          if status.get(a, {}).get("active", a <= N)]
                done = K in truth and all(K in est[a] for a in active)
                if done or (world_end is not None and now - world_end > 5.0):
                    break
                if now >= next_progress and truth:
                    next_progress = now + 1.0
                    k = max(truth)
                    say(f"step {k}/{K}  drops {sum(s['drops'] for s in status.values())}  "
                        f"late {sum(s['late'] for s in status.values())}")
            # final statuses: ask the agents to stop, then read what they said last
            children.signal_all(signal.SIGTERM)
            deadline = time.monotonic() + 5.0
            while children.running() and time.monotonic() < deadline:
                peer.wait(timeout=0.1)
                drain()
            drain()
    except KeyboardInterrupt:
        interrupted = True
        failure = "interrupted"
    except RunFailed as exc:
        failure = str(exc)
    finally:
        children.stop_all()
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGINT, old_int)
    wall = time.monotonic() - t_begin

    # ---- results ------------------------------------------------------------------
    steps_done = sorted(k for k in truth if k <= K)
    active = [a for a in range(1, M + 1) if est[a]]
    mse = []
    for k in steps_done:
        errs = [np.mean((est[a][k] - truth[k]) ** 2) for a in active if k in est[a]]
        mse.append(float(np.mean(errs)) if errs else float("nan"))
    mse = np.array(mse)
    tail = max(1, K // 4)
    mse_steady = float(np.mean(mse[-tail:])) if len(mse) else float("nan")
    predicted = loop.mse_steady(scenario.process_noise, scenario.measurement_noise) \
        if rho < 1 else float("inf")
    last = {a: status.get(a, {}) for a in range(1, M + 1)}
    summary = {
        "scenario": scenario.name,
        "run": run_id,
        "ports": ports,
        "seed": args.seed,
        "steps": int(steps_done[-1]) if steps_done else -1,
        "steps_requested": K,
        "step_ms": step_ms,
        "deadline_ms": deadline_ms,
        "agents": N,
        "standby": scenario.standby,
        "delays": args.delays,
        "rho_closed_loop": rho,
        "mse_steady": mse_steady,
        "mse_steady_predicted": predicted,
        "drops": sum(s.get("drops", 0) for s in last.values()),
        "late": sum(s.get("late", 0) for s in last.values()),
        "malformed": sum(s.get("malformed", 0) for s in last.values()),
        "recorder_malformed": stats.total_dropped,
        "sensor_missed": sum(s.get("sensor", {}).get("missed", 0) for s in last.values()),
        "learned_delays": {str(a): {str(j): d for j, d in s.get("delays", {}).items()}
                           for a, s in last.items() if s},
        "hop_ms": {str(a): s.get("hop_ms") for a, s in last.items() if s.get("hop_ms")},
        "cpu_s": {c.name: c.cpu_s for c in children.children.values()},
        "wall_s": wall,
        "exit_status": {c.name: c.returncode for c in children.children.values()},
        "orphans": [c.name for c in children.children.values() if c.returncode is None],
    }
    status_code = 0
    if failure:
        summary["error"] = failure
        status_code = 130 if interrupted else 1
    if args.check_simulator and not failure:
        diff, how = _compare_simulator(scenario, G, K, args.seed, delays, truth, est, active,
                                       mse, steps_done)
        summary["max_rel_diff_vs_simulator"] = diff
        summary["simulator_compared"] = how
        if not diff <= CHECK_TOL:
            status_code = 1
    _write_run_folder(out, summary, steps_done, mse, predicted)
    _save_estimates(out / "estimates.npz", steps_done, truth, est, active, scenario.n)
    summary["out"] = str(out)
    if args.json:
        print(json.dumps(to_jsonable(summary), indent=2))
    else:
        print(f"{scenario.name}: {summary['steps']} steps, {N} agents, mse_steady "
              f"{mse_steady:.4g} (predicted {predicted:.4g}), drops {summary['drops']}, "
              f"late {summary['late']}, malformed {summary['malformed']}"
              + (f", max_rel_diff_vs_simulator {summary['max_rel_diff_vs_simulator']:.3g}"
                 if "max_rel_diff_vs_simulator" in summary else "")
              + f"\nrun folder: {out}")
    if failure:
        print(f"socmon up: {failure}", file=sys.stderr)
    return status_code


def _compare_simulator(scenario, G, K, seed, delays, truth, est, active, mse, steps_done):
    """Largest difference to ``design.simulate`` (trial 0, same seed and delays).

    With per-agent estimates from the simulator: ``max |xhat_live - xhat_sim| / max(1, |x_k|)``
    (infinity norms). Otherwise the per-step MSE: ``max |mse_live - mse_sim| / mse_sim``,
    which is stricter (an error of size e carries |x|/e times more relative weight).
    """
    import numpy as np

    from design.simulate import simulate

    res = simulate(scenario, G, steps=K, trials=1, seed=seed, delays=delays,
                   coordinates="absolute", record_estimates=True)
    if len(steps_done) != K + 1:
        return float("inf"), "incomplete run"
    sim_est = getattr(res, "estimates", None)
    if sim_est is not None:
        worst = 0.0
        for k in steps_done:
            scale = max(1.0, float(np.abs(truth[k]).max()))
            for i, a in enumerate(active):
                if k in est[a]:
                    d = float(np.abs(est[a][k] - np.asarray(sim_est)[0, k, i]).max())
                    worst = max(worst, d / scale)
        return worst, "estimates"
    sim_mse = np.asarray(res.mse)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(mse - sim_mse) / np.abs(sim_mse)
    return float(np.nanmax(rel)) if np.all(np.isfinite(mse)) else float("inf"), "mse per step"


def _save_estimates(path, steps_done, truth, est, agents, n):
    """truth (K+1, n) and estimates (K+1, agents, n), NaN where nothing was received."""
    import numpy as np

    X = np.full((len(steps_done), n), np.nan)
    E = np.full((len(steps_done), len(agents), n), np.nan)
    for r, k in enumerate(steps_done):
        X[r] = truth[k]
        for c, a in enumerate(agents):
            if k in est[a]:
                E[r, c] = est[a][k]
    np.savez(path, step=np.array(steps_done, dtype=int), truth=X, estimates=E,
             agents=np.array(agents, dtype=int))


def _write_run_folder(out, summary, steps_done, mse, predicted):
    import csv
    import json
    import sys

    from ._common import to_jsonable

    (out / "summary.json").write_text(json.dumps(to_jsonable(summary), indent=2) + "\n")
    with open(out / "mse.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "mse"])
        for k, m in zip(steps_done, mse):
            w.writerow([k, repr(float(m))])
    (out / "mse.json").write_text(json.dumps(to_jsonable(
        {"step": steps_done, "mse": list(mse)})) + "\n")
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return
    import numpy as np

    mse = np.asarray(mse, dtype=float)
    ok = np.isfinite(mse) & (mse > 0) & (mse < 1e250)
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogy(np.asarray(steps_done)[ok], mse[ok], lw=1, label="live run")
    if predicted and predicted != float("inf"):
        ax.axhline(predicted, color="k", ls="--", lw=0.8, label="predicted steady MSE")
    ax.set_xlabel("step")
    ax.set_ylabel("MSE (mean over agents and states)")
    ax.set_title(f"{summary['scenario']}: {summary['agents']} agents, seed {summary['seed']}")
    ax.legend()
    try:
        fig.tight_layout()
        fig.savefig(out / "mse.png", dpi=110)
    except (OverflowError, ValueError) as exc:  # e.g. a diverged run's huge values
        print(f"up: warning: no mse.png ({type(exc).__name__}: {exc})", file=sys.stderr)
    finally:
        plt.close(fig)
