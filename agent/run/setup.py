"""A live run set up from what the user asked: its configuration checked and its testbed.

:func:`run_config` turns the flags of ``socmon up`` (and ``chaos``) into a
:class:`agent.run.local.RunConfig`, every problem an :class:`agent.run.inputs.InputError`
naming the flag; :func:`parse_faults` reads the scheduled faults and :func:`check_faults`
holds them to one set of checks; :func:`testbed_for` makes and removes the network
namespaces of ``--netns``; :func:`live_run` sets a run up, runs it, checks it and writes
its folder; :func:`simulator_problem` says what ``--check-simulator`` found;
:func:`exit_status` says how a finished run ends."""

from __future__ import annotations

import contextlib
import signal
import sys
from dataclasses import dataclass

from agent.run.inputs import (
    DEFAULT_OBJECTIVE,
    InputError,
    check_run_flags,
    default_design,
    load_gains_arg,
    load_scenario_arg,
    timing_arg,
)


def run_config(args, say, prog="up", design_progress=None):
    """A :class:`agent.run.local.RunConfig` from the flags of ``up`` (and ``chaos``), every
    flag checked (:class:`InputError` naming it), the run folder prepared, the gains loaded
    or designed (``design_progress``: as for :func:`design.gain_design.design_gains`) and
    saved in it."""
    import time
    from pathlib import Path

    import numpy as np

    from design.closed_loop import closed_loop_for
    from design.errors import ScenarioError
    from design.gains import gains_meta, save_gains
    from design.scenario import resolve_delays

    from agent.run.local import RunConfig
    from agent.monitor.core import MonitorConfig
    from agent.run.folder import InvalidRunFolder, prepare_run_folder

    scenario = load_scenario_arg(args.scenario)
    if args.steps < 1:
        raise InputError(f"--steps: must be >= 1, got {args.steps}")
    check_run_flags(args)
    try:
        delays = resolve_delays(scenario, args.delays)
    except ScenarioError as exc:
        raise InputError(str(exc)) from None
    step_ms = args.step_ms if args.step_ms is not None else scenario.step_ms
    if not step_ms > 0:
        raise InputError(f"--step-ms: must be > 0, got {step_ms}")
    slow = step_period_warning(step_ms)
    if slow:
        print(f"{prog}: warning: {slow}", file=sys.stderr, flush=True)
    deadline_ms = args.deadline_ms if args.deadline_ms is not None else (
        30000.0 if getattr(args, "check_simulator", False) else step_ms)
    if not deadline_ms > 0:
        raise InputError(f"--deadline-ms: must be > 0, got {deadline_ms}")
    if not 0 <= args.drop < 1:
        raise InputError(f"--drop: must be a probability in [0, 1), got {args.drop}")
    timing_arg(step_s=step_ms / 1000.0, lead_steps=MonitorConfig.lead_steps,
               hang_timeout_s=args.hang_timeout, hang_timeout_max_s=args.hang_timeout_max,
               start_timeout_s=args.start_timeout)
    if getattr(args, "router", False) and getattr(args, "secure", False):
        raise InputError("--router: not with --secure (the access control of a secured run "
                           "names the process at the other end of each link, which a router "
                           "would hide)")
    if args.no_monitor and getattr(args, "monitors", None) is not None:
        raise InputError("--monitors: no monitor runs with --no-monitor (give one or the other)")
    faults = parse_faults(args, scenario) if prog == "up" else ()
    for f in faults:
        note = f.standby_note(scenario.N)
        if note:
            print(f"{prog}: note: {note}", file=sys.stderr, flush=True)
    if getattr(args, "netns_prefix", None) is not None:
        from agent.testbed.netns import check_prefix

        if not args.netns:
            raise InputError("--netns-prefix: only with --netns")
        try:
            check_prefix(args.netns_prefix)
        except ValueError as exc:
            raise InputError(f"--netns-prefix: {exc}") from None
    if getattr(args, "netns", False) and getattr(args, "listen", None) is not None:
        raise InputError("--listen: not with --netns: each process is on a host of its own "
                         "(10.200.0.x) and the run's entry is chosen there; up prints it and "
                         "writes it in run.json (connect)")
    if getattr(args, "netns", False):
        # what would stop the testbed, said before a gain is designed or a file written
        from agent.testbed.netns import prefix_taken, unavailable_reason

        why = unavailable_reason() or (prefix_taken(args.netns_prefix)
                                       if args.netns_prefix is not None else None)
        if why is not None:
            raise InputError(f"--netns: {why}", status=1)
    run_id, listen = check_run_endpoint(getattr(args, "run", None),
                                        getattr(args, "listen", None),
                                        getattr(args, "secure", False))
    out = Path(args.out) if args.out else Path("runs") / (
        f"{scenario.name}-{time.strftime('%Y%m%d-%H%M%S')}-s{args.seed}")
    try:
        prepare_run_folder(out, overwrite=getattr(args, "overwrite", False))
    except InvalidRunFolder as exc:
        raise InputError(f"--out: {exc}") from None
    meta = {}
    if args.gains:
        source = load_gains_arg(args.gains, scenario, force=getattr(args, "force_gains", False))
        G, method = list(source.G), "file"
        # what the file says of itself (docs/json.md, gains `meta`): its design, and its
        # exact steady MSE when it was designed for the delays of this run
        meta = {"source": str(Path(args.gains).resolve()),
                **{k: source.meta[k] for k in ("objective",) if k in source.meta},
                **({"source_method": source.meta["method"]} if "method" in source.meta
                   else {})}
        designed_for = source.meta.get("delays")
        if designed_for is not None and "mse_steady_exact" in source.meta and \
                np.array_equal(np.asarray(designed_for), np.asarray(delays)):
            meta["mse_steady_exact"] = source.meta["mse_steady_exact"]
    else:
        say(f"designing gains with the default method (objective {DEFAULT_OBJECTIVE}) ...")
        res = default_design(scenario, delays, progress=design_progress)
        G, method = list(res.G), "default"
        meta = {"objective": res.objective, "mse_steady_exact": res.mse_steady}
    from design.gap import gap_warnings

    for line in gap_warnings(scenario, G, delays):
        print(f"{prog}: warning: {line}", file=sys.stderr, flush=True)
    gains_path = (out / "gains.npz").resolve()
    rho = closed_loop_for(scenario, G, delays).spectral_radius()
    save_gains(gains_path, G, gains_meta(scenario, method, delays, rho, **meta))
    scen_arg = str(Path(args.scenario).resolve()) if Path(args.scenario).is_file() \
        else args.scenario
    return RunConfig(scenario=scenario, scenario_arg=scen_arg, G=list(G), gains_path=gains_path,
                     delays=delays, delays_spec=args.delays, steps=args.steps, seed=args.seed,
                     step_ms=step_ms, deadline_ms=deadline_ms, out=out,
                     monitor=not args.no_monitor, monitors=getattr(args, "monitors", None) or 2,
                     precompute=not getattr(args, "no_precompute", False),
                     hang_timeout=args.hang_timeout, hang_timeout_max=args.hang_timeout_max,
                     drop=args.drop, faults=tuple(faults), start_timeout=args.start_timeout,
                     secure=getattr(args, "secure", False), run_id=run_id, listen=listen,
                     router=getattr(args, "router", False),
                     record_every=getattr(args, "record_every", 1))


#: Below this step period (ms) no agent keeps the pace: its own CPU time a step in a live
#: run is 0.7-1.1 ms (docs/runtime.md, the agent's step at 4 and 10 ms).
MIN_SUSTAINED_STEP_MS = 1.0


def step_period_warning(step_ms: float) -> str | None:
    """The warning for a step period below :data:`MIN_SUSTAINED_STEP_MS`, or None: the run
    goes on at the machine's pace (no hard limit)."""
    if step_ms >= MIN_SUSTAINED_STEP_MS:
        return None
    return (f"--step-ms {step_ms:g}: below {MIN_SUSTAINED_STEP_MS:g} ms, less than an agent's "
            "own CPU time a step in a live run (0.7-1.1 ms measured, docs/runtime.md): the "
            "period will not be sustained, and most neighbour estimates will be late or "
            "dropped")


def check_run_endpoint(run_id, listen, secure) -> tuple:
    """``--run`` and ``--listen`` of ``up`` checked: a valid run id; a ``tcp/HOST:PORT``
    (``tls/`` with ``--secure``) endpoint whose port is free now."""
    import re
    import socket

    from broker_free_net.config import InvalidNetConfig, NetConfig


    try:                         # the transport's own rules for run ids and endpoints
        # (the keys of a --secure run are made later: its tls/ endpoint is checked as a
        # plain one, which alone may go without keys)
        NetConfig(run=run_id, listen=None if listen is None else (
            "tcp/" + listen.removeprefix("tls/") if secure else listen,))
    except InvalidNetConfig as exc:
        raise InputError(exc.as_flag()) from None
    if listen is None:
        return run_id, None
    scheme = "tls" if secure else "tcp"
    m = re.fullmatch(scheme + r"/(\[[0-9a-fA-F:]+\]|[^:/\s]+):([0-9]{1,5})", listen)
    if not m or not 0 < int(m.group(2)) < 65536:
        raise InputError(f"--listen: expected {scheme}/HOST:PORT"
                           f"{' (--secure runs speak tls)' if secure else ''}, got {listen!r}")
    host = m.group(1).strip("[]")
    try:
        with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as sock:
            sock.bind((host, int(m.group(2))))
    except OSError as exc:
        raise InputError(f"--listen: cannot listen on {listen}: {exc.strerror}") from None
    return run_id, listen


@contextlib.contextmanager
def testbed_for(args, config, say):
    """With ``--netns``: a testbed with one host per process of the run, removed after it
    (also when the run fails or is interrupted); else None."""
    if not getattr(args, "netns", False):
        yield None
        return
    from agent.testbed.netns import Testbed, TestbedError, host_names, unavailable_reason

    why = unavailable_reason()
    if why is not None:
        raise InputError(f"--netns: {why}", status=1)
    testbed = Testbed(host_names(config.M, router=config.router), prefix=args.netns_prefix)

    def on_term(*_):                  # SIGTERM outside the run itself: still clean up
        raise KeyboardInterrupt

    old_term = signal.signal(signal.SIGTERM, on_term)   # before the first namespace
    try:
        try:
            testbed.create()
        except TestbedError as exc:
            raise InputError(f"--netns: {exc}", status=1) from None
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


#: The ``--fault`` kinds whose VALUE says how much (0, the default, would inject nothing).
VALUED = {"delay": "steps of delay", "drop": "the probability of a loss",
          "lie": "noise std-devs off", "bias": "noise std-devs off",
          "drift": "noise std-devs each 100 steps", "noise": "times the sensor's noise"}
#: The kinds that last SECONDS and are then undone (0 would inject nothing); the others
#: act at their step and take no SECONDS.
LASTING = {"stop": "how long the agent is stopped", "sensor": "how long its readings stop",
           "partition": "how long its links are cut", "delay": "how long its links are delayed",
           "drop": "how long its links drop", "linkdown": "how long the link is down",
           "worldstop": "how long the process is stopped",
           "monitorstop": "how long the process is stopped"}
#: A fault's SECONDS is below this (an hour: longer is no fault of a run but its end).
MAX_FAULT_S = 3600.0


def parse_faults(args, scenario) -> list:
    """The faults of ``--kill``, ``--stop``, ``--kill-monitor`` and ``--fault``: each read
    by its own flag's syntax, then all held to the same checks (:func:`check_faults`)."""
    M = scenario.N + scenario.standby
    from agent.run.local import FAULT_KINDS, PROCESS_FAULTS, Fault

    def agent_id(text, flag):
        if not (text.isascii() and text.isdigit()) or not 1 <= int(text) <= M:
            raise InputError(f"{flag}: {text!r} is not an agent id in 1..{M}")
        return int(text)

    def step(text, flag):
        if not (text.isascii() and text.isdigit()) or int(text) < 1:
            raise InputError(f"{flag}: {text!r} is not a step >= 1")
        return int(text)

    read = []                    # (fault, the flag that asked for it, its value)
    for spec in args.kill:
        parts = spec.split(":")
        if len(parts) != 2:
            raise InputError(f"--kill: expected STEP:AGENTS (e.g. 300:1,2), got {spec!r}")
        k = step(parts[0], "--kill")
        read += [(Fault(k, "crash", agent_id(a.strip(), "--kill")), "--kill", spec)
                 for a in parts[1].split(",")]
    for spec in args.stop:
        parts = spec.split(":")
        if len(parts) != 3:
            raise InputError(f"--stop: expected STEP:AGENT:SECONDS (e.g. 300:2:5), got {spec!r}")
        try:
            secs = float(parts[2])
        except ValueError:
            raise InputError(f"--stop: SECONDS is a number, got {spec!r}") from None
        read.append((Fault(step(parts[0], "--stop"), "stop", agent_id(parts[1], "--stop"),
                           secs), "--stop", spec))
    if args.kill_monitor is not None:
        read.append((Fault(args.kill_monitor, "monitor"), "--kill-monitor",
                     str(args.kill_monitor)))
    for spec in getattr(args, "fault", []):
        parts = spec.split(":")
        kind = parts[0]
        if kind not in FAULT_KINDS or kind == "crash" or not 2 <= len(parts) <= 5:
            raise InputError(f"--fault: expected KIND:STEP[:AGENT[:SECONDS[:VALUE]]] with "
                               f"KIND one of {', '.join(k for k in FAULT_KINDS if k != 'crash')}"
                               f", got {spec!r}")
        k = step(parts[1], "--fault")
        if kind in PROCESS_FAULTS:
            if len(parts) > 2 and parts[2] not in ("", "0"):
                proc = {"worldstop": "world"}.get(kind, "monitor")
                raise InputError(f"--fault: {kind} acts on the {proc} and takes no agent, "
                                   f"got {spec!r}")
            a = 0
        elif len(parts) > 2:
            a = agent_id(parts[2], "--fault")
        else:
            raise InputError(f"--fault: {kind} needs an agent, got {spec!r}")
        try:
            secs = float(parts[3]) if len(parts) > 3 else 0.0
            value = float(parts[4]) if len(parts) > 4 else 0.0
        except ValueError:
            raise InputError(f"--fault: SECONDS and VALUE are numbers, got {spec!r}") from None
        read.append((Fault(k, kind, a, secs, value), "--fault", spec))
    return check_faults(read, args)


def check_faults(read, args) -> list:
    """The faults of ``read`` (``(fault, flag, value)``, in the order given) sorted by step,
    every one held to the same checks whatever flag asked for it, the first broken one an
    :class:`InputError` naming that flag and its value: within the run's steps; SECONDS in
    (0, :data:`MAX_FAULT_S`) for the kinds that last (:data:`LASTING`), none for the others;
    a VALUE for the kinds that take one (:data:`VALUED`), none for the others; linkdown
    only with ``--netns``; none on a monitor with ``--no-monitor``; only those the simulator
    replays with ``--check-simulator``; no agent killed twice."""
    from agent.run.fault_kinds import MONITOR_FAULTS, REPLAYED_FAULTS, REPLAYED_WORDS

    killed = {}                  # agent -> (flag, value) that kills it
    for f, flag, spec in read:
        kind, secs, value = f.kind, f.seconds, f.value
        if f.step < 1:
            raise InputError(f"{flag}: step {f.step} is not a step >= 1")
        if f.step > args.steps:
            raise InputError(f"{flag}: step {f.step} is after the run's last step "
                               f"({args.steps}, --steps): the fault would never happen")
        if kind in LASTING and not secs > 0:
            raise InputError(f"{flag}: {kind} needs SECONDS > 0 ({LASTING[kind]}), "
                               f"got {spec!r}")
        if kind in LASTING and not secs < MAX_FAULT_S:
            raise InputError(f"{flag}: {kind} needs SECONDS below {MAX_FAULT_S:g}, "
                               f"got {spec!r}")
        if kind not in LASTING and secs != 0:
            raise InputError(f"{flag}: {kind} acts at its step and takes no SECONDS (those "
                               f"of {', '.join(LASTING)} do), got {spec!r}")
        if kind in VALUED and not 0 < value <= 1_000_000:
            raise InputError(f"{flag}: {kind} needs VALUE > 0 ({VALUED[kind]}; "
                               f"{kind}:STEP:AGENT:SECONDS:VALUE), got {spec!r}")
        if kind not in VALUED and value != 0:
            raise InputError(f"{flag}: {kind} takes no VALUE (those of "
                               f"{', '.join(VALUED)} do), got {spec!r}")
        if kind == "drop" and not value <= 1:
            raise InputError(f"{flag}: drop VALUE is a probability in [0, 1], got {spec!r}")
        if kind == "delay" and value != int(value):
            raise InputError(f"{flag}: delay VALUE is a whole number of steps, got {spec!r}")
        if kind in MONITOR_FAULTS and getattr(args, "no_monitor", False):
            raise InputError(f"{flag}: no monitor runs with --no-monitor (give one or the "
                               f"other), got {spec!r}")
        if kind == "linkdown" and not getattr(args, "netns", False):
            raise InputError(f"{flag}: linkdown brings a host's link down and needs "
                               f"--netns, got {spec!r}")
        if getattr(args, "check_simulator", False) and kind not in REPLAYED_FAULTS:
            raise InputError(f"--check-simulator: the simulator does not replay {flag} "
                               f"{spec} ({f.describe()}); it replays {REPLAYED_WORDS} only "
                               "(give one or the other)")
        if kind in ("crash", "kill"):
            if f.agent in killed:
                first = " ".join(killed[f.agent])
                raise InputError(f"{flag}: agent {f.agent} is killed twice ({first} and "
                                   f"{flag} {spec})")
            killed[f.agent] = (flag, spec)
    return sorted(f for f, _, _ in read)


@dataclass
class FinishedRun:
    """A live run done: its configuration, record and summary, its exit status (0 ok, 1 a
    negative result: failed, diverged, a role lost for good, the simulator check failed;
    130 interrupted; :data:`agent.run.folder.EXIT_FOLDER` the run folder could not be
    written) and the problems to say on stderr."""

    config: object
    record: object
    summary: dict
    status: int
    problems: list


def live_run(args, say, design_progress=None, on_designed=None) -> FinishedRun:
    """``socmon up``: set the run up from its flags (:func:`run_config`), run it on its
    testbed, summarize what the processes did, check it against the simulator when asked,
    and write the run folder. ``on_designed``: called once the gains are known."""
    import dataclasses

    from agent.run.folder import EXIT_FOLDER, RunFolderError
    from agent.run.summary import (
        compare_simulator,
        links_impaired,
        run_and_summarize,
        write_run_folder,
    )

    config = run_config(args, say, design_progress=design_progress)
    if on_designed is not None:
        on_designed()
    with testbed_for(args, config, say) as testbed:
        if testbed is not None:
            config = dataclasses.replace(config, testbed=testbed)
        rec, summary, steps_done, mse, predicted = run_and_summarize(config, say)
    status = exit_status(rec, summary)
    problems = [rec.failure] if rec.failure else []
    if args.check_simulator and not rec.failure:
        diff, how = compare_simulator(config, rec, steps_done)
        summary["max_rel_diff_vs_simulator"] = diff
        summary["simulator_compared"] = how
        problem = simulator_problem(diff, how, links_impaired(
            summary.get("events", []), config.scenario, config.delays))
        if problem:
            status = status or 1
            problems.append(problem)
    try:
        write_run_folder(config.out, summary, steps_done, mse, predicted, recording=rec,
                         n=config.scenario.n)
    except RunFolderError as exc:   # a full disk: the summary still goes to stdout
        problems.append(f"run folder: {exc}")
        status = status or EXIT_FOLDER
    summary["out"] = str(config.out)
    return FinishedRun(config, rec, summary, status, problems)


def simulator_problem(diff: float, how: str, impaired=()) -> str | None:
    """What ``--check-simulator`` says of a finished run compared by
    :func:`agent.run.summary.compare_simulator` (``diff, how``): None when it equals the
    simulator's replay; that it was not compared when the run could not be replayed (what
    only the run could tell, e.g. a reassignment without a scripted crash); else by how much
    it differs, and, when links were impaired during the run (``impaired``: ``(step,
    agent)``, :func:`agent.run.summary.links_impaired`), that the simulator does not
    replay that.

    >>> simulator_problem(1e-15, "estimates (201 compared)") is None
    True
    >>> simulator_problem(float("inf"), "incomplete run")
    "--check-simulator: the run was not compared with the simulator's replay: incomplete run"
    """
    from agent.run.summary import CHECK_TOL, was_compared

    if not was_compared(how):
        return f"--check-simulator: the run was not compared with the simulator's replay: {how}"
    if diff <= CHECK_TOL:
        return None
    text = (f"--check-simulator: the run differs from the simulator's replay by {diff:.3g} "
            f"(relative; at most {CHECK_TOL:g} allowed): {how}")
    if impaired:
        step, agent = impaired[0]
        more = f", {len(impaired)} changes in all" if len(impaired) > 1 else ""
        text += (f"; link impairments were set during the run (the links into agent {agent} "
                 f"at step {step}{more}: socmon inject, or anyone with the operator key), "
                 "and the simulator does not replay them")
    return text


def exit_status(rec, summary: dict) -> int:
    """How a finished run ends: 130 interrupted, 1 when it failed, diverged, or lost an
    active role for good (each said in the summary's warnings), else 0. A failure is
    also written in the summary (``error``)."""
    status = 0
    if rec.failure:
        summary["error"] = rec.failure
        status = 130 if rec.interrupted else 1
    if summary.get("diverged_at") is not None:
        status = status or 1
    if any(f.get("detected") is False and f.get("role") == "active"
           for f in summary.get("failures", [])):
        status = status or 1
    return status
