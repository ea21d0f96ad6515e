"""``socmon up SCENARIO``: a whole live run on this machine, recorded into a run folder."""

from __future__ import annotations

import contextlib
import signal
import sys

from agent.protocol.timing import DEFAULT as TIMING

HELP = "run world + one process per agent on this machine, record, and write a run folder"



def add_arguments(parser) -> None:
    from agent.cli._common import add_force_gains_argument, add_scenario_argument, int_flag

    add_scenario_argument(parser)
    parser.add_argument("--steps", type=int, default=200, help="steps to run (default 200)")
    parser.add_argument("--gains", help="gains file (.npz); default: design with the default method")
    add_force_gains_argument(parser)
    parser.add_argument("--seed", type=int, default=0, help="run seed (default 0)")
    parser.add_argument("--out", help="run folder (default runs/<scenario>-<time>-s<seed>); "
                             "a folder holding an earlier run is refused")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace the earlier run in --out (its files only)")
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
    parser.add_argument("--start-timeout", type=float, default=TIMING.start_timeout_s,
                        help="seconds allowed for every process to be up "
                             f"(default {TIMING.start_timeout_s:g})")
    parser.add_argument("--quiet", action="store_true", help="no progress on stderr")
    parser.add_argument("--no-monitor", action="store_true",
                        help="run without the monitor (a failed agent is then never replaced)")
    parser.add_argument("--monitors", type=int_flag(lo=1, hi=9), default=2, metavar="N",
                        help="monitors started (default 2): the first acts, the others stand "
                             "by and take over when it dies or is paused")
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
    parser.add_argument("--fault", action="append", default=[],
                        metavar="KIND:STEP[:AGENT[:SECONDS[:VALUE]]]",
                        help="any scheduled fault (repeatable): kill, stop, hang (the agent's "
                             "loop stops, its token stays), sensor (its readings stop for "
                             "SECONDS), partition, delay (VALUE steps), drop (VALUE "
                             "probability), monitor, linkdown (the agent's host's link down "
                             "for SECONDS; with --netns), worldstop and monitorstop (the "
                             "world or the monitor SIGSTOPped for SECONDS: "
                             "worldstop:STEP::SECONDS), monitorsgone (every monitor "
                             "SIGKILLed for good); see docs/monitor.md")
    parser.add_argument("--hang-timeout", type=float, default=TIMING.hang_timeout_s,
                        metavar="S", help="the monitor's hang timeout (default "
                        f"{TIMING.hang_timeout_s:g} s; above twice the status period "
                        f"{TIMING.status_s:g} s)")
    parser.add_argument("--hang-timeout-max", type=float, default=TIMING.hang_timeout_max_s,
                        metavar="S",
                        help="the hang timeout grows with the statuses' observed pace up to S "
                             f"seconds (default {TIMING.hang_timeout_max_s:g}; equal to "
                             "--hang-timeout keeps it fixed; docs/monitor.md)")
    parser.add_argument("--run", default=None, metavar="ID",
                        help="run id (key prefix socmon/<ID>/; default a fresh one); printed "
                             "and written in RUN_FOLDER/run.json")
    parser.add_argument("--listen", default=None, metavar="ENDPOINT",
                        help="endpoint of this command's own peer, the one every process of "
                             "the run and every attached tool connects to (default "
                             "tcp/127.0.0.1:<free port>, tls/ with --secure)")
    parser.add_argument("--secure", action="store_true",
                        help="a fresh key set for this run (RUN_FOLDER/keys): mutual TLS between "
                             "every process and access control on every peer "
                             "(docs/security.md)")
    parser.add_argument("--netns", action="store_true",
                        help="each process on its own host: a network namespace per process, "
                             "wired by veth pairs to a bridge in a switch namespace, 10.200.0.x "
                             "addresses; removed after the run (needs root; docs/runtime.md)")
    parser.add_argument("--netns-prefix", default=None, metavar="PREFIX",
                        help="namespace names PREFIX-<host> (default sm<pid>)")
    parser.add_argument("--router", action="store_true",
                        help="start a zenoh router (socmon router) and make every process its "
                             "client: one link per process instead of the peer mesh's "
                             "N(N-1)/2 (docs/transport.md)")


def run(args) -> int:
    from agent.cli._common import run_command

    return run_command(lambda: _up(args))


def run_config(args, say, prog="up"):
    """A :class:`agent.run.local.RunConfig` from the flags of ``up`` (and ``chaos``)."""
    import time
    from pathlib import Path

    from design.closed_loop import closed_loop_for
    from design.errors import ScenarioError
    from design.gains import gains_meta, save_gains
    from design.scenario import resolve_delays

    from agent.run.local import RunConfig
    from agent.monitor.core import MonitorConfig
    from agent.run.folder import InvalidRunFolder, prepare_run_folder
    from agent.cli._common import CommandError, check_run_flags, load_scenario_arg, timing_arg
    from agent.cli.agent_cmd import gains_for

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
        30000.0 if getattr(args, "check_simulator", False) else step_ms)
    if not deadline_ms > 0:
        raise CommandError(f"--deadline-ms: must be > 0, got {deadline_ms}")
    if not 0 <= args.drop < 1:
        raise CommandError(f"--drop: must be a probability in [0, 1), got {args.drop}")
    timing_arg(step_s=step_ms / 1000.0, lead_steps=MonitorConfig.lead_steps,
               hang_timeout_s=args.hang_timeout, hang_timeout_max_s=args.hang_timeout_max,
               start_timeout_s=args.start_timeout)
    if getattr(args, "router", False) and getattr(args, "netns", False):
        raise CommandError("--router: not with --netns (the router would need a host of its "
                           "own on the testbed)")
    if getattr(args, "router", False) and getattr(args, "secure", False):
        raise CommandError("--router: not with --secure (the access control of a secured run "
                           "names the process at the other end of each link, which a router "
                           "would hide)")
    faults = parse_faults(args, scenario) if prog == "up" else ()
    if getattr(args, "netns_prefix", None) is not None:
        from agent.testbed.netns import check_prefix

        if not args.netns:
            raise CommandError("--netns-prefix: only with --netns")
        try:
            check_prefix(args.netns_prefix)
        except ValueError as exc:
            raise CommandError(f"--netns-prefix: {exc}") from None
    run_id, listen = check_run_endpoint(getattr(args, "run", None),
                                        getattr(args, "listen", None),
                                        getattr(args, "secure", False))
    out = Path(args.out) if args.out else Path("runs") / (
        f"{scenario.name}-{time.strftime('%Y%m%d-%H%M%S')}-s{args.seed}")
    try:
        prepare_run_folder(out, overwrite=getattr(args, "overwrite", False))
    except InvalidRunFolder as exc:
        raise CommandError(f"--out: {exc}") from None
    if args.gains:
        G = gains_for(scenario, args.gains, delays, getattr(args, "force_gains", False))
        method = "file"
    else:
        say("designing gains with the default method ...")
        from agent.cli._progress import ProgressLine

        line = ProgressLine("up", enabled=not (getattr(args, "quiet", False)
                                              or getattr(args, "json", False)))
        try:
            G = gains_for(scenario, None, delays, progress=line.design)
        finally:
            line.close()
        method = "default"
    from design.gap import gap_warnings

    for line in gap_warnings(scenario, G, delays):
        print(f"{prog}: warning: {line}", file=sys.stderr, flush=True)
    gains_path = (out / "gains.npz").resolve()
    rho = closed_loop_for(scenario, G, delays).spectral_radius()
    save_gains(gains_path, G, gains_meta(scenario, method, delays, rho))
    scen_arg = str(Path(args.scenario).resolve()) if Path(args.scenario).is_file() \
        else args.scenario
    return RunConfig(scenario=scenario, scenario_arg=scen_arg, G=list(G), gains_path=gains_path,
                     delays=delays, delays_spec=args.delays, steps=args.steps, seed=args.seed,
                     step_ms=step_ms, deadline_ms=deadline_ms, out=out,
                     monitor=not args.no_monitor, monitors=getattr(args, "monitors", 2),
                     hang_timeout=args.hang_timeout, hang_timeout_max=args.hang_timeout_max,
                     drop=args.drop, faults=tuple(faults), start_timeout=args.start_timeout,
                     secure=getattr(args, "secure", False), run_id=run_id, listen=listen,
                     router=getattr(args, "router", False))


def check_run_endpoint(run_id, listen, secure) -> tuple:
    """``--run`` and ``--listen`` of ``up`` checked: a valid run id; a ``tcp/HOST:PORT``
    (``tls/`` with ``--secure``) endpoint whose port is free now."""
    import re
    import socket

    from broker_free_net.config import InvalidNetConfig, NetConfig

    from agent.cli._common import CommandError

    try:                         # the transport's own rules for run ids and endpoints
        NetConfig(run=run_id, listen=None if listen is None else (listen,))
    except InvalidNetConfig as exc:
        raise CommandError(f"--{exc.field}: {str(exc).removeprefix(exc.field + ': ')}") \
            from None
    if listen is None:
        return run_id, None
    scheme = "tls" if secure else "tcp"
    m = re.fullmatch(scheme + r"/(\[[0-9a-fA-F:]+\]|[^:/\s]+):([0-9]{1,5})", listen)
    if not m or not 0 < int(m.group(2)) < 65536:
        raise CommandError(f"--listen: expected {scheme}/HOST:PORT"
                           f"{' (--secure runs speak tls)' if secure else ''}, got {listen!r}")
    host = m.group(1).strip("[]")
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
            sock.bind((host, int(m.group(2))))
    except OSError as exc:
        raise CommandError(f"--listen: cannot listen on {listen}: {exc.strerror}") from None
    return run_id, listen


@contextlib.contextmanager
def testbed_for(args, config, say):
    """With ``--netns``: a testbed with one host per process of the run, removed after it
    (also when the run fails or is interrupted); else None."""
    if not getattr(args, "netns", False):
        yield None
        return
    from agent.testbed.netns import Testbed, TestbedError, host_names, unavailable_reason
    from agent.cli._common import CommandError

    why = unavailable_reason()
    if why is not None:
        raise CommandError(f"--netns: {why}", status=1)
    testbed = Testbed(host_names(config.M), prefix=args.netns_prefix)

    def on_term(*_):                  # SIGTERM outside the run itself: still clean up
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_term)   # before the first namespace
    try:
        try:
            testbed.create()
        except TestbedError as exc:
            raise CommandError(f"--netns: {exc}", status=1) from None
        say(f"testbed: {len(testbed.hosts)} hosts in namespaces {testbed.prefix}-*, switch "
            f"{testbed.switch}")
        yield testbed
    finally:
        try:
            testbed.close()
        except TestbedError as exc:
            print(f"socmon up: --netns: not every namespace could be deleted ({exc})",
                  file=sys.stderr)
        signal.signal(signal.SIGTERM, old_term)


def _up(args) -> int:
    import dataclasses
    import json
    import sys

    from agent.run.summary import (
        CHECK_TOL,
        compare_simulator,
        failure_lines,
        run_and_summarize,
        save_estimates,
        write_run_folder,
    )
    from agent.run.folder import EXIT_FOLDER, RunFolderError
    from agent.cli._common import to_jsonable

    def say(text):
        if not args.quiet:
            print(f"up: {text}", file=sys.stderr, flush=True)

    config = run_config(args, say)
    s = config.scenario
    with testbed_for(args, config, say) as testbed:
        if testbed is not None:
            config = dataclasses.replace(config, testbed=testbed)
        rec, summary, steps_done, mse, predicted = run_and_summarize(config, say)
    status_code = 0
    if rec.failure:
        summary["error"] = rec.failure
        status_code = 130 if rec.interrupted else 1
    if summary.get("diverged_at") is not None:
        status_code = status_code or 1       # a negative result: said in the warnings
    if any(f.get("detected") is False and f.get("role") == "active"
           for f in summary.get("failures", [])):
        status_code = status_code or 1       # a role lost for good: said in the warnings
    if args.check_simulator and not rec.failure:
        diff, how = compare_simulator(config, rec, steps_done)
        summary["max_rel_diff_vs_simulator"] = diff
        summary["simulator_compared"] = how
        if not diff <= CHECK_TOL:
            status_code = 1
    folder_error = None
    try:
        write_run_folder(config.out, summary, steps_done, mse, predicted, assigns=rec.assigns)
        active = [a for a in range(1, config.M + 1) if rec.est[a]]
        save_estimates(config.out / "estimates.npz", steps_done, rec.truth, rec.est, active,
                       s.n)
    except RunFolderError as exc:   # a full disk: the summary still goes to stdout
        folder_error = exc
    summary["out"] = str(config.out)
    for warning in summary.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    if args.json:
        print(json.dumps(to_jsonable(summary), indent=2))
    else:
        exact = summary.get("mse_steady_exact_in_force")
        print(f"{s.name}: {summary['steps']} steps, {s.N} agents, mse_steady "
              f"{summary['mse_steady']:.4g} (predicted "
              + (f"{exact:.4g} for the configuration in force" if exact is not None
                 else "n/a: the window spans a switch")
              + (f"; DIVERGED at step {summary['diverged_at']}"
                 if summary.get("diverged_at") is not None else "") + "), drops "
              f"{summary['drops']}, late {summary['late']}, malformed {summary['malformed']}"
              + (f", max_rel_diff_vs_simulator {summary['max_rel_diff_vs_simulator']:.3g}"
                 if "max_rel_diff_vs_simulator" in summary else ""))
        for line in failure_lines(summary):
            print(line)
        print(f"run folder: {config.out}")
    if rec.failure:
        print(f"socmon up: {rec.failure}", file=sys.stderr)
    if folder_error is not None:
        print(f"socmon up: run folder: {folder_error}", file=sys.stderr)
        return status_code or EXIT_FOLDER
    return status_code


def parse_faults(args, scenario) -> list:
    """``--kill``, ``--stop``, ``--kill-monitor`` checked against the scenario."""
    from agent.cli._common import CommandError

    M = scenario.N + scenario.standby
    from agent.run.local import Fault

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
    faults = [Fault(k, "crash", a) for a, k in out["kill"].items()]
    faults += [Fault(k, "stop", a, secs) for a, (k, secs) in out["stop"].items()]
    if args.kill_monitor is not None:
        faults.append(Fault(args.kill_monitor, "monitor"))
    from agent.run.local import FAULT_KINDS, PROCESS_FAULTS

    for spec in getattr(args, "fault", []):
        parts = spec.split(":")
        kind = parts[0]
        if kind not in FAULT_KINDS or kind == "crash" or not 2 <= len(parts) <= 5:
            raise CommandError(f"--fault: expected KIND:STEP[:AGENT[:SECONDS[:VALUE]]] with "
                               f"KIND one of {', '.join(k for k in FAULT_KINDS if k != 'crash')}"
                               f", got {spec!r}")
        k = step(parts[1], "--fault")
        if kind in PROCESS_FAULTS:
            if len(parts) > 2 and parts[2] not in ("", "0"):
                proc = {"worldstop": "world"}.get(kind, "monitor")
                raise CommandError(f"--fault: {kind} acts on the {proc} and takes no agent, "
                                   f"got {spec!r}")
            a = 0
        else:
            a = agent_id(parts[2], "--fault") if len(parts) > 2 else 0
        if kind not in PROCESS_FAULTS and not a:
            raise CommandError(f"--fault: {kind} needs an agent, got {spec!r}")

        if kind == "linkdown" and not getattr(args, "netns", False):
            raise CommandError(f"--fault: linkdown brings a host's link down and needs "
                               f"--netns, got {spec!r}")
        try:
            secs = float(parts[3]) if len(parts) > 3 else 0.0
            value = float(parts[4]) if len(parts) > 4 else 0.0
        except ValueError:
            raise CommandError(f"--fault: SECONDS and VALUE are numbers, got {spec!r}") from None
        if not (0 <= secs < 3600 and 0 <= value <= 1_000_000):
            raise CommandError(f"--fault: SECONDS in [0, 3600) and VALUE >= 0, got {spec!r}")
        if kind == "drop" and not value <= 1:
            raise CommandError(f"--fault: drop VALUE is a probability in [0, 1], got {spec!r}")
        if kind == "delay" and value != int(value):
            raise CommandError(f"--fault: delay VALUE is a whole number of steps, got {spec!r}")
        if kind in ("worldstop", "monitorstop") and not secs > 0:
            raise CommandError(f"--fault: {kind} needs SECONDS > 0 (how long the process is "
                               f"stopped), got {spec!r}")
        if kind == "linkdown" and not secs > 0:
            raise CommandError(f"--fault: linkdown needs SECONDS > 0 (how long the link is "
                               f"down), got {spec!r}")
        faults.append(Fault(k, kind, a, secs, value))
    flags = {"crash": "--kill", "stop": "--stop", "monitor": "--kill-monitor"}
    for f in faults:
        if f.step > args.steps:
            raise CommandError(f"{flags.get(f.kind, '--fault')}: step {f.step} is after the "
                               f"run's last step ({args.steps}, --steps): the fault would "
                               "never happen")
    return sorted(faults)
