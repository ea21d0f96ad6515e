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
    parser.add_argument("--no-monitor", action="store_true",
                        help="run without the monitor (a failed agent is then never replaced)")
    parser.add_argument("--drop", type=float, default=0.0,
                        help="probability that an estimate is lost on a link, drawn from the "
                             "seed as the simulator draws it (default 0)")
    parser.add_argument("--kill", action="append", default=[], metavar="STEP:AGENTS",
                        help="scripted crash: agents (e.g. 1,2) publish step STEP-1 and SIGKILL "
                             "themselves (repeatable)")
    parser.add_argument("--stop", action="append", default=[], metavar="STEP:AGENT:SECONDS",
                        help="SIGSTOP agent AGENT once the world reaches STEP, SIGCONT it "
                             "SECONDS later (repeatable)")
    parser.add_argument("--kill-monitor", type=int, default=None, metavar="STEP",
                        help="SIGKILL the monitor once the world reaches STEP and start it again")
    parser.add_argument("--hang-timeout", type=float, default=1.0, metavar="S",
                        help="the monitor's hang timeout (default 1.0 s)")


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

    faults = parse_faults(args, scenario)
    if not 0 <= args.drop < 1:
        raise CommandError(f"--drop: must be a probability in [0, 1), got {args.drop}")
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
    ports = [free_port() for _ in range(M + 3)]
    ep = [f"tcp/127.0.0.1:{p}" for p in ports]
    children = Children(out / "logs")
    truth, est, status = {}, {a: {} for a in range(1, M + 1)}, {}
    rosters = [(0, tuple(range(1, N + 1)), 0)]      # (activate_at, ids, epoch)
    assigns = {}                                   # (agent, epoch) -> decoded assignment
    events = []                                    # what happened to the processes
    pending_cont = {}                              # agent -> time to SIGCONT
    done_faults = set()
    stats = MessageStats()
    est_schema, truth_schema = wire.est_schema(scenario.n), wire.truth_schema(scenario.n)
    roster_schema, ctl_schema = wire.roster_schema(), wire.ctl_schema(scenario.n)
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
            ctl_in = peer.subscribe(keys.any_agent_pattern(run_id, "ctl"), maxlen=1 << 12)
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
                if args.drop:
                    argv += ["--drop", repr(args.drop)]
                if a in faults["kill"]:
                    argv += ["--crash-at", str(faults["kill"][a])]
                children.start(f"agent-{a}", argv)
            monitor_argv = ["monitor", scen_arg, "--run", run_id, "--connect", ep[0],
                            "--listen", ep[M + 2], "--gains", str(gains_path),
                            "--delays", args.delays, "--hang-timeout", str(args.hang_timeout),
                            "--step-ms", str(step_ms),
                            "--events", str((out / "events.jsonl").resolve())]
            if not args.no_monitor:
                children.start("monitor", monitor_argv)
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
                for item in ctl_in.drain():
                    if item.key == keys.ctl_key(run_id, 0):
                        m = try_decode(item.payload, roster_schema, stats)
                        if m is not None and m["epoch"] > rosters[-1][2]:
                            rosters.append((m["activate_at"], tuple(m["ids"]), m["epoch"]))
                    else:
                        m = try_decode(item.payload, ctl_schema, stats)
                        if m is not None:
                            assigns.setdefault((m["agent"], m["epoch"]), m)

            world_end = None
            next_progress = time.monotonic() + 1.0
            start_deadline = time.monotonic() + args.start_timeout + 30.0
            while True:
                peer.wait(timeout=0.2)
                drain()
                for child in children.reap():
                    if child.name == "world" and child.returncode == 0:
                        world_end = time.monotonic()
                    elif child.name == "world" or (world_end is None and args.no_monitor
                                                   and not faults["any"]):
                        raise RunFailed(f"{child.name} exited with status {child.returncode} "
                                        f"before the end of the run; its log ends:\n"
                                        f"{children.tail(child.name)}")
                    elif world_end is None:
                        k_now = max(truth) if truth else -1
                        events.append({"process": child.name, "exit_status": child.returncode,
                                       "step": k_now, "t": time.time()})
                        say(f"{child.name} exited with status {child.returncode} at step "
                            f"{k_now}; the run goes on")
                now = time.monotonic()
                k_now = max(truth) if truth else -1
                for a, (k_stop, secs) in faults["stop"].items():
                    if k_now >= k_stop and ("stop", a) not in done_faults:
                        done_faults.add(("stop", a))
                        _signal_child(children, f"agent-{a}", signal.SIGSTOP)
                        pending_cont[a] = now + secs
                        events.append({"process": f"agent-{a}", "signal": "SIGSTOP",
                                       "step": k_now, "t": time.time()})
                        say(f"agent {a} stopped (SIGSTOP) at step {k_now} for {secs:g} s")
                for a, t_cont in list(pending_cont.items()):
                    if now >= t_cont:
                        del pending_cont[a]
                        _signal_child(children, f"agent-{a}", signal.SIGCONT)
                        events.append({"process": f"agent-{a}", "signal": "SIGCONT",
                                       "step": k_now, "t": time.time()})
                        say(f"agent {a} resumed (SIGCONT) at step {k_now}")
                if (args.kill_monitor is not None and k_now >= args.kill_monitor
                        and "monitor" not in done_faults and not args.no_monitor):
                    done_faults.add("monitor")
                    _signal_child(children, "monitor", signal.SIGKILL)
                    events.append({"process": "monitor", "signal": "SIGKILL", "step": k_now,
                                   "t": time.time()})
                    _wait_exit(children, "monitor", 10.0)
                    children.start("monitor-2", monitor_argv)
                    say(f"monitor killed (SIGKILL) at step {k_now} and started again")
                if not truth and now > start_deadline:
                    raise RunFailed(f"the clock did not start within {args.start_timeout:g} s; "
                                    f"world log:\n{children.tail('world')}")
                running = {c.name for c in children.running()}
                in_force = set(rosters[-1][1])
                active = [a for a in range(1, M + 1) if f"agent-{a}" in running
                          and a in in_force and status.get(a, {}).get("active", a <= N)]
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
        children.signal_all(signal.SIGCONT)      # a stopped child cannot act on SIGTERM
        children.stop_all()
        signal.signal(signal.SIGTERM, old_term)
        signal.signal(signal.SIGINT, old_int)
    wall = time.monotonic() - t_begin

    # ---- results ------------------------------------------------------------------
    steps_done = sorted(k for k in truth if k <= K)
    active = [a for a in range(1, M + 1) if est[a]]

    def in_force(k):
        return [ids for at, ids, _ in rosters if at <= k][-1]

    mse = []
    for k in steps_done:
        errs = [np.mean((est[a][k] - truth[k]) ** 2) for a in in_force(k) if k in est[a]]
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
        "monitor": not args.no_monitor,
        "events": events,
        "final_roles": {str(a): {"active": st.get("active"), "epoch": st.get("epoch"),
                                 "measure": st.get("measure")}
                        for a, st in last.items() if st},
    }
    summary.update(_failures(out / "events.jsonl", events, rosters, assigns, scenario,
                             delays, steps_done, mse, K, G))
    status_code = 0
    if failure:
        summary["error"] = failure
        status_code = 130 if interrupted else 1
    if args.check_simulator and not failure:
        diff, how = _compare_simulator(scenario, G, K, args.seed, delays, truth, est, active,
                                       mse, steps_done, drop=args.drop,
                                       recovery=_recovery_record(faults, rosters, assigns,
                                                                 scenario, delays))
        summary["max_rel_diff_vs_simulator"] = diff
        summary["simulator_compared"] = how
        if not diff <= CHECK_TOL:
            status_code = 1
    _write_run_folder(out, summary, steps_done, mse, predicted, rosters)
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


def parse_faults(args, scenario) -> dict:
    """``--kill``, ``--stop``, ``--kill-monitor`` checked against the scenario."""
    from ._common import CommandError

    M = scenario.N + scenario.standby
    out = {"kill": {}, "stop": {}, "any": False}

    def agent_id(text, flag):
        if not (text.isascii() and text.isdigit()) or not 1 <= int(text) <= M:
            raise CommandError(f"{flag}: {text!r} is not an agent id in 1..{M}")
        return int(text)

    def step(text, flag):
        if not (text.isascii() and text.isdigit()) or int(text) < 1:
            raise CommandError(f"{flag}: {text!r} is not a step >= 1")
        return int(text)

    for spec in args.kill:
        parts = spec.split(":")
        if len(parts) != 2:
            raise CommandError(f"--kill: expected STEP:AGENTS (e.g. 300:1,2), got {spec!r}")
        k = step(parts[0], "--kill")
        for a in parts[1].split(","):
            a = agent_id(a.strip(), "--kill")
            if a in out["kill"]:
                raise CommandError(f"--kill: agent {a} is killed twice")
            out["kill"][a] = k
    for spec in args.stop:
        parts = spec.split(":")
        if len(parts) != 3:
            raise CommandError(f"--stop: expected STEP:AGENT:SECONDS (e.g. 300:2:5), got {spec!r}")
        try:
            secs = float(parts[2])
        except ValueError:
            secs = -1.0
        if not 0 < secs < 3600:
            raise CommandError(f"--stop: SECONDS must be in (0, 3600), got {parts[2]!r}")
        out["stop"][agent_id(parts[1], "--stop")] = (step(parts[0], "--stop"), secs)
    if args.kill_monitor is not None and args.kill_monitor < 1:
        raise CommandError(f"--kill-monitor: must be a step >= 1, got {args.kill_monitor}")
    out["any"] = bool(out["kill"] or out["stop"] or args.kill_monitor is not None)
    return out


def _signal_child(children, name, sig):
    import os

    child = children.children.get(name)
    if child is not None and child.returncode is None:
        try:
            os.killpg(child.proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


def _wait_exit(children, name, timeout):
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        children.reap()
        if children.children[name].returncode is not None:
            return True
        time.sleep(0.01)
    return False


def _specs_in_force(rosters, assigns, scenario, G0, epoch=None):
    """``(ids, {id: RoleSpec})`` of the last roster (or of the one of ``epoch``), from the
    assignments recorded up to that epoch."""
    import numpy as np

    from design.roster import Roster, role_specs
    from design.roster import RoleSpec

    specs = role_specs(Roster.initial(scenario), G0)
    for (agent, e), m in sorted(assigns.items(), key=lambda kv: kv[0][1]):
        if epoch is not None and e > epoch:
            continue
        specs[agent] = RoleSpec(agent, tuple(m["measure"]), dict(m["neighbours"]),
                                float(m["self_weight"]), np.asarray(m["gain"]),
                                m.get("take_over"))
    if epoch is not None:
        return next(ids for _, ids, ep in rosters if ep == epoch), specs
    return rosters[-1][1], specs


def _recovery_record(faults, rosters, assigns, scenario, delays):
    """What the simulator needs to replay a run with one scripted crash and its recovery."""
    return {"faults": faults, "rosters": rosters, "assigns": assigns}


def _failures(events_path, events, rosters, assigns, scenario, delays, steps_done, mse, K, G0):
    """``failures``, ``recovered``, MSE after recovery (live and exact) for the summary."""
    import json
    import math

    import numpy as np

    records = []
    try:
        with open(events_path) as f:
            for line in f:
                try:
                    records.append(json.loads(line))
                except ValueError:
                    continue
    except OSError:
        pass
    deaths = {}
    for e in events:
        name = e.get("process", "")
        if name.startswith("agent-") and (e.get("exit_status") is not None or
                                          e.get("signal") == "SIGSTOP"):
            deaths.setdefault(int(name.split("-")[1]), e)
    failures = []
    reassigns = [r for r in records if r.get("kind") == "reassign"]
    for v in [r for r in records if r.get("kind") == "verdict"]:
        entry = {"agent": v["agent"], "cause": v["cause"], "evidence": v["evidence"],
                 "detected_step": v["step"]}
        death = deaths.get(v["agent"])
        if death is not None and death.get("signal") == "SIGSTOP":
            entry["detection_ms"] = 1e3 * (v.get("detected_t", v["t"]) - death["t"])
        r = next((r for r in reassigns if v["agent"] in r.get("failed", [])), None)
        if r is not None:
            entry.update(epoch=r["epoch"], activate_at=r["activate_at"],
                         precomputed=r.get("precomputed"))
            rep = [x for x in r["replacements"] if x["failed"] == v["agent"]]
            entry["replacement"] = ({"agent": rep[0]["by"], "node": rep[0]["to"]} if rep
                                    else None)
        failures.append(entry)
    out = {"failures": failures, "rosters": [{"activate_at": at, "ids": list(ids),
                                               "epoch": ep} for at, ids, ep in rosters]}
    if len(rosters) > 1:
        at = rosters[-1][0]
        ids, specs = _specs_in_force(rosters, assigns, scenario, G0)
        recovered = all(a in specs for a in ids) and steps_done and steps_done[-1] >= at
        out["recovered"] = bool(recovered)
        after = [m for k, m in zip(steps_done, mse) if k >= at]
        tail = after[-max(1, len(after) // 4):] if after else []
        out["mse_steady_after_recovery"] = float(np.mean(tail)) if tail else float("nan")
        try:
            from design.closed_loop import closed_loop_for
            from design.roster import link_delay_table, roster_from_specs

            table = link_delay_table(scenario, delays)
            new, G, D = roster_from_specs(scenario, table, ids, specs)
            loop = closed_loop_for(new, G, D)
            rho = loop.spectral_radius()
            out["rho_closed_loop_after_recovery"] = rho
            out["mse_steady_predicted_after_recovery"] = (
                loop.mse_steady(new.process_noise, new.measurement_noise)
                if rho < 1 else math.inf)
        except Exception as exc:       # noqa: BLE001 - reported, the run's data is kept
            out["mse_steady_predicted_after_recovery"] = None
            out.setdefault("warnings", []).append(f"no exact prediction after recovery: {exc}")
    elif failures:
        out["recovered"] = False
    return out


def _compare_simulator(scenario, G, K, seed, delays, truth, est, active, mse, steps_done,
                       drop=0.0, recovery=None):
    """Largest difference to ``design.simulate`` (trial 0, same seed, delays and drops).

    ``max_k max_a |xhat_live - xhat_sim| / max(1, |x_k|)`` (infinity norms) over every
    estimate both computed. With one scripted crash (``--kill``) and the monitor's
    recovery, the simulator replays the crash at the same step and the recorded
    reassignment (its ``activate_at``, roles and gains).
    """
    import numpy as np

    from design.roster import link_delay_table, roster_from_specs
    from design.simulate import Recovery, simulate

    fail = recover = None
    if recovery is not None and recovery["faults"]["kill"]:
        kills = recovery["faults"]["kill"]
        if len(set(kills.values())) != 1 or recovery["faults"]["stop"]:
            return float("inf"), "the simulator replays one scripted crash step only"
        f = next(iter(kills.values()))
        fail = (f, sorted(a - 1 for a in kills))
        rosters = [r for i, r in enumerate(recovery["rosters"])
                   if i == 0 or r[1] != recovery["rosters"][i - 1][1]]   # re-issues
        table = link_delay_table(scenario, delays)
        chain = []
        for i, (at, ids, epoch) in enumerate(rosters[1:], start=1):
            _, specs = _specs_in_force(recovery["rosters"], recovery["assigns"], scenario, G,
                                       epoch=epoch)
            new, G_new, D_new = roster_from_specs(scenario, table, ids, specs)
            before = set(rosters[i - 1][1])
            replaces = {a: specs[a].take_over - 1 for a in ids
                        if a not in before and specs[a].take_over is not None}
            chain.append(Recovery(new, G_new, tuple(ids), replaces=replaces, delays=D_new,
                                  activate_at=at))
        recover = chain or None
    res = simulate(scenario, G, steps=K, trials=1, seed=seed, delays=delays, drop=drop,
                   fail=fail, recover=recover, coordinates="absolute", record_estimates=True)
    if len(steps_done) != K + 1:
        return float("inf"), "incomplete run"
    sim_est = np.asarray(res.estimates)[0]
    worst, compared = 0.0, 0
    for k in steps_done:
        scale = max(1.0, float(np.abs(truth[k]).max()))
        for c, a in enumerate(res.estimate_ids):
            if k in est.get(a, {}) and np.isfinite(sim_est[k, c]).all():
                d = float(np.abs(est[a][k] - sim_est[k, c]).max())
                worst = max(worst, d / scale)
                compared += 1
    return worst, f"estimates ({compared} compared)"


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


def _write_run_folder(out, summary, steps_done, mse, predicted, rosters=()):
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
    after = summary.get("mse_steady_predicted_after_recovery")
    if after and after != float("inf"):
        ax.axhline(after, color="tab:green", ls=":", lw=0.9,
                   label="predicted after recovery")
    for i, f in enumerate(summary.get("failures", [])):
        ax.axvline(f["detected_step"], color="tab:red", lw=0.8, ls="--",
                   label="detected" if i == 0 else None)
        if f.get("activate_at") is not None:
            ax.axvline(f["activate_at"], color="tab:green", lw=0.8,
                       label="reassigned" if i == 0 else None)
    for i, e in enumerate(e for e in summary.get("events", [])
                          if e.get("exit_status") is not None or e.get("signal")):
        ax.axvline(e["step"], color="k", lw=0.6, alpha=0.6,
                   label="fault" if i == 0 else None)
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
