"""Chaos runs: a random fault schedule drawn from a seed, and the invariants a run must keep.

:func:`draw_schedule` turns ``(scenario, seed, duration, kinds, rate)`` into a list of
:class:`agent.run.local.Fault` (the same seed gives the same schedule, on any machine);
``socmon chaos`` runs it live with the monitor (:class:`agent.run.local.LocalRun`) and
:func:`check_invariants` reads the recording. Every violation names the invariant, the
step and the evidence.

Invariants (the bounds are in :class:`Bounds`):

- ``recovery``: after a fault that takes an agent of the configuration in force out
  (kill, crash, a stop or partition longer than the hang timeout), whenever the plan on
  that configuration says recovery is possible with the standbys of that moment (not
  dead, hung, or convicted and not yet rejoined), a configuration without it that
  measures every parent SCC is in force within ``recovery_steps``;
- ``fencing``: no estimate that a receiver would accept comes from an agent outside the
  configuration in force (at most one agent acts for a role at any epoch): an outsider
  may only publish under an older epoch, which every receiver drops;
- ``processes``: only processes that were killed exit with a non-zero status; none is
  left running;
- ``error``: outside ``settle_steps`` after each fault or reassignment, the mean MSE over
  ``window`` steps stays below ``error_factor`` times the exact steady MSE of the
  configuration in force (its gains, the run's delays);
- ``convictions``: the monitor convicts only agents that were made faulty (killed,
  stopped, hung, silenced sensors, partitioned), and every agent that dies holding a role.

Examples
--------
>>> from design.scenario import load_scenario
>>> s = load_scenario("paper-14-live")
>>> a = draw_schedule(s, seed=3, duration=600, kinds=("kill", "stop", "monitor"), rate=4)
>>> a == draw_schedule(s, seed=3, duration=600, kinds=("kill", "stop", "monitor"), rate=4)
True
>>> all(f.kind in ("kill", "stop", "monitor") for f in a)
True
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from agent.run.fault_kinds import WRONG_KINDS
from agent.run.local import Fault
# the scheduling slack before a verdict is required lives with the rule it serves
from agent.run.summary import VERDICT_SLACK_S, conviction_bound_s  # noqa: F401

__all__ = ["CHAOS_KINDS", "DEFAULT_KINDS", "Bounds", "draw_schedule", "check_schedule_flags",
           "check_invariants", "Violation"]

#: The kinds a chaos run draws unless told otherwise (``crash`` is up's scripted kill).
DEFAULT_KINDS = ("kill", "stop", "hang", "sensor", "monitor", "partition", "delay", "drop")
#: Every kind it can draw: the defaults, and agents that keep running but are wrong (the
#: residual tests' work, docs/residuals.md): ``lie`` (it publishes its estimates a few
#: noise std-devs off), ``bias`` (its sensor reads a few std-devs off), from their step to
#: the run's end.
CHAOS_KINDS = DEFAULT_KINDS + WRONG_KINDS


@dataclass(frozen=True)
class Bounds:
    """The stated bounds of the invariants (steps of the run)."""

    recovery_steps: int = 150       # 3 s at 20 ms: hang timeout + lead + confirmations
    settle_steps: int = 150         # error is judged this long after a fault or activation
    window: int = 50
    error_factor: float = 5.0
    warmup: int = 80                # no fault before this step
    gap: int = 160                  # at least this many steps between two faults


@dataclass(frozen=True)
class Violation:
    invariant: str
    step: int
    evidence: str

    def to_dict(self) -> dict:
        return {"invariant": self.invariant, "step": self.step, "evidence": self.evidence}


def check_schedule_flags(args) -> None:
    """``--rate`` and ``--duration`` of ``socmon chaos``, live or simulated: an
    :class:`agent.run.inputs.InputError` naming the flag when one is out of range."""
    from agent.run.inputs import InputError

    if not 0 <= args.rate <= 6.25:          # also refuses nan
        raise InputError(f"--rate: must be in [0, 6.25] faults per 1000 steps, got {args.rate}")
    if args.duration < 100:
        raise InputError(f"--duration: must be >= 100 steps, got {args.duration}")


def draw_schedule(scenario, seed: int, duration: int, kinds=DEFAULT_KINDS, rate: float = 3.0,
                  step_ms: float = 20.0, bounds: Bounds = Bounds()) -> list:
    """A fault schedule for ``duration`` steps: about ``rate`` faults per 1000 steps.

    Faults are at least ``bounds.gap`` steps apart, after ``bounds.warmup``; a killed
    agent is never a target again; at least one agent of each parent SCC's measurers or
    a standby is left alive (the schedule never kills the last agents), so recovery stays
    possible. Durations (stop, partition, delay, drop) are drawn in seconds; the size of
    a lie or a bias in noise std-devs (2 to 8: from inside the noise to far out), one
    of them at most per agent.
    """
    rng = np.random.default_rng([int(seed), 0xC4A05])
    kinds = tuple(kinds)
    if not kinds:
        return []
    M = scenario.N + scenario.standby
    alive = list(range(1, M + 1))
    count = rng.poisson(rate * duration / 1000.0)
    slots = list(range(bounds.warmup, max(bounds.warmup, duration - bounds.gap // 2),
                       bounds.gap))
    rng.shuffle(slots)
    steps = sorted(s + int(rng.integers(0, bounds.gap // 4)) for s in slots[:count])
    out = []
    skewed = set()                  # agents that lie or whose sensor is biased
    for k in steps:
        kind = kinds[int(rng.integers(len(kinds)))]
        if kind == "monitor":
            out.append(Fault(k, "monitor"))
            continue
        if kind == "monitorstop":
            out.append(Fault(k, "monitorstop", 0, float(np.round(rng.uniform(0.5, 6.0), 2))))
            continue
        # keep at least two agents alive: one to measure, one to talk to
        if kind in ("kill", "hang") and len(alive) <= 2:
            kind = "stop" if "stop" in kinds else None
        if kind is None:
            continue
        agent = int(alive[int(rng.integers(len(alive)))])
        if kind in ("kill", "hang"):
            alive.remove(agent)
            out.append(Fault(k, kind, agent))
        elif kind == "sensor":
            out.append(Fault(k, "sensor", agent, float(np.round(rng.uniform(1.0, 4.0), 2))))
        elif kind == "stop":
            out.append(Fault(k, "stop", agent, float(np.round(rng.uniform(0.3, 3.0), 2))))
        elif kind == "partition":
            out.append(Fault(k, "partition", agent, float(np.round(rng.uniform(1.0, 4.0), 2))))
        elif kind == "delay":
            out.append(Fault(k, "delay", agent, float(np.round(rng.uniform(1.0, 2.5), 2)),
                             float(int(rng.integers(1, 6)))))
        elif kind == "slow":            # simulated runs only (agent.run.simulated)
            out.append(Fault(k, "slow", agent, float(np.round(rng.uniform(1.0, 4.0), 2)),
                             float(np.round(rng.uniform(0.5, 3.0), 2))))
        elif kind == "drop":
            out.append(Fault(k, "drop", agent, float(np.round(rng.uniform(1.0, 2.5), 2)),
                             float(np.round(rng.uniform(0.1, 0.5), 2))))
        elif kind in WRONG_KINDS and agent not in skewed:
            skewed.add(agent)
            out.append(Fault(k, kind, agent, 0.0, float(np.round(rng.uniform(2.0, 8.0), 2))))
    return out


def configuration_key(scenario, *parts) -> tuple:
    """Every field of ``scenario`` and ``parts`` (arrays, lists of arrays, other values) as
    a hashable key: what a cache of a pure function of them is keyed by."""
    def key(x):
        if isinstance(x, np.ndarray):
            return x.dtype.str, x.shape, x.tobytes()
        if isinstance(x, (list, tuple)):
            return tuple(key(y) for y in x)
        return x

    s = scenario
    return (s.name, key(s.A), s.labels, s.process_noise, s.measure, s.measurement_noise,
            s.standby, key(s.W), key(np.asarray(s.delays)), s.step_ms, s.source,
            *(key(p) for p in parts))


#: the exact MSE of a configuration by :func:`configuration_key`: the runs of a batch of
#: schedules meet the same configurations (the initial one in every run)
_EXACT_MSE: dict = {}


def _exact_mse(scenario, G, D) -> float:
    from design.closed_loop import exact_performance
    from design.errors import SocmonError

    key = configuration_key(scenario, list(G), np.asarray(D))
    if key not in _EXACT_MSE:
        try:
            _EXACT_MSE[key] = exact_performance(scenario, G, D).mse_or_inf
        except (SocmonError, ValueError):
            _EXACT_MSE[key] = math.inf
    return _EXACT_MSE[key]


def _roster_at(rosters, k):
    return [r for r in rosters if r[0] <= k][-1]


def check_invariants(config, rec, summary, steps, mse, bounds: Bounds = Bounds()) -> list:
    """Every violation of the module's invariants in one recorded run."""
    from design.errors import SocmonError
    from design.graph import influence_structure
    from design.roster import Roster, link_delay_table, replan, roster_from_specs

    from agent.run.summary import specs_in_force

    c = config
    s = c.scenario
    out = []
    step_s = c.step_ms / 1000.0
    structure = influence_structure(s.A)
    parents = {int(p) for p in structure.parents}
    table = link_delay_table(s, c.delays)

    # the configurations in force, as the recorder heard them, with their roles
    configs = []
    for at, ids, epoch in rec.rosters:
        _, specs = specs_in_force(rec.rosters, rec.assigns, s, c.G, epoch=epoch)
        try:
            new, G, D = roster_from_specs(s, table, ids, specs)
        except SocmonError:
            # the recorder missed an assignment of this epoch: nothing to judge it by
            continue
        covered = {int(structure.labels[v]) for m in new.measure for v in m}
        configs.append({"at": at, "ids": tuple(ids), "epoch": epoch, "scenario": new, "G": G,
                        "D": D, "covers": parents <= covered})

    # -- recovery ------------------------------------------------------------------------
    last = steps[-1] if steps else -1
    taken_out = []
    for f in c.faults:
        # a stop is convicted after the hang timeout (from its last status, a status period
        # before the stop); a partition after its listeners' ages pass the silent bound
        # (the link's delay plus silent_steps) and then the hang timeout: one rule with the
        # summary's no_verdict_due (agent.run.summary.conviction_bound_s)
        bound = conviction_bound_s(f.kind, c.hang_timeout, step_s, int(table.max()))
        if f.kind in ("kill", "crash", "hang") or (bound is not None and f.seconds > bound):
            taken_out.append(f)
    for f in taken_out:
        in_force = _roster_at(rec.rosters, f.step)
        if f.agent not in in_force[1]:
            continue
        cfg = next((x for x in configs if x["epoch"] == in_force[2]), None)
        if cfg is None:
            continue
        # the standbys then: not dead or hung, and not convicted without having rejoined
        # since (a convicted agent is on probation: the monitor does not take it back)
        roster = Roster(cfg["scenario"], cfg["ids"], tuple(
            a for a in range(1, c.M + 1) if a not in cfg["ids"]
            and not any(g.kind in ("kill", "crash", "hang") and g.agent == a
                        and g.step <= f.step for g in c.faults)
            and not any(v.get("agent") == a and v.get("detected_step") is not None
                        and v["detected_step"] <= f.step
                        and (v.get("rejoined_step") or math.inf) > f.step
                        for v in summary.get("failures", []))), table, cfg["D"])
        try:
            plan, nxt = replan(roster, [f.agent], numerical=False)
        except SocmonError:
            continue
        if nxt is None or not plan.structurally_observable_after:
            continue
        if f.step + bounds.recovery_steps > last:
            continue
        ok = any(x["at"] <= f.step + bounds.recovery_steps and x["at"] > f.step
                 and f.agent not in x["ids"] and x["covers"] for x in configs)
        if not ok:
            out.append(Violation("recovery", f.step, f"{f.kind} of agent {f.agent}: no "
                                 f"configuration without it measuring every parent SCC within "
                                 f"{bounds.recovery_steps} steps"))

    # -- fencing ---------------------------------------------------------------------------
    # an agent outside the configuration in force may still publish (a stopped agent that
    # resumes catches up on its old role before it hears the roster), but only under an
    # older epoch, which every receiver drops; the estimate a replacement takes over is
    # published stamped activate_at - 1 under the new epoch
    starts = {(a, at - 1) for at, ids, _ in rec.rosters[1:] for a in ids}
    for a, by_step in rec.est.items():
        for k in sorted(by_step):
            at, ids, epoch = _roster_at(rec.rosters, k)
            e = rec.est_epoch[a].get(k, 0)
            if a not in ids and e >= epoch and (a, k) not in starts:
                out.append(Violation("fencing", k, f"agent {a} published step {k} under epoch "
                                     f"{e}, outside the configuration of epoch {epoch} "
                                     f"{list(ids)} (in force from step {at})"))
                break
        epochs = [rec.est_epoch[a][k] for k in sorted(rec.est_epoch.get(a, {}))]
        down = next((i for i in range(1, len(epochs)) if epochs[i] < epochs[i - 1]), None)
        if down is not None:
            out.append(Violation("fencing", sorted(rec.est_epoch[a])[down],
                                 f"agent {a}'s epoch went down from {epochs[down - 1]} to "
                                 f"{epochs[down]}"))
    rosters_epochs = [ep for _, _, ep in rec.rosters]
    if rosters_epochs != sorted(set(rosters_epochs)):
        out.append(Violation("fencing", -1, f"roster epochs not increasing: {rosters_epochs}"))
    # -- processes -------------------------------------------------------------------------
    killed = {f"agent-{f.agent}" for f in c.faults if f.kind in ("kill", "crash")}
    monitors = {name for name in summary["exit_status"] if name.startswith("monitor")}
    for name, code in summary["exit_status"].items():
        if code not in (0, None) and name not in killed and not (
                name in monitors and any(f.kind in ("monitor", "monitorsgone")
                                         for f in c.faults)):
            out.append(Violation("processes", -1, f"{name} exited with status {code}"))
    for name in summary["orphans"]:
        out.append(Violation("processes", -1, f"{name} was still running at the end"))

    # -- error -----------------------------------------------------------------------------
    marks = sorted([f.step for f in c.faults] + [x["at"] for x in configs[1:]]
                   + [v["detected_step"] for v in summary.get("failures", [])
                      if v.get("detected_step") is not None])
    # a lie or a sensor bias skews the error for as long as its agent holds a role (an
    # undetected one, or one only alerted, for good): no bound is stated there
    skewed = []                     # [start, end) of the steps judged by no bound
    ends = [at for at, _, _ in rec.rosters[1:]] + [math.inf]
    for f in c.faults:
        if f.kind in WRONG_KINDS:
            skewed += [(max(at, f.step), end + bounds.settle_steps)
                       for (at, ids, _), end in zip(rec.rosters, ends)
                       if f.agent in ids and end > f.step]
    mse_at = dict(zip(steps, mse))
    predicted = {x["epoch"]: _exact_mse(x["scenario"], x["G"], x["D"]) for x in configs}
    k = 0
    while k + bounds.window <= last:
        span = range(k, k + bounds.window)
        quiet = all(not (m <= j < m + bounds.settle_steps) for j in span for m in marks) \
            and k >= bounds.settle_steps \
            and not any(a <= j < b for j in (span[0], span[-1]) for a, b in skewed)
        if quiet:
            epochs = {_roster_at(rec.rosters, j)[2] for j in span}
            if len(epochs) == 1:
                e = epochs.pop()
                vals = [mse_at[j] for j in span if j in mse_at and math.isfinite(mse_at[j])]
                bound = bounds.error_factor * predicted.get(e, math.inf)
                if vals and np.mean(vals) > bound:
                    out.append(Violation("error", k, f"mean MSE {np.mean(vals):.4g} over steps "
                                         f"{k}..{k + bounds.window - 1} > {bounds.error_factor:g}"
                                         f" x exact {predicted[e]:.4g} (epoch {e})"))
        k += bounds.window

    # -- convictions -------------------------------------------------------------------------
    faulty = {f.agent for f in c.faults
              if f.kind in ("kill", "crash", "stop", "hang", "sensor", "partition", "lie",
                            "bias")}
    for v in summary.get("failures", []):
        if v.get("detected") is False:
            if v.get("role") == "active":
                out.append(Violation("convictions", v["died_step"],
                                     f"agent {v['agent']} died holding a role and was never "
                                     f"convicted ({v['why']})"))
        elif v["agent"] and v["agent"] not in faulty:
            out.append(Violation("convictions", v["detected_step"],
                                 f"agent {v['agent']} convicted ({v['cause']}: "
                                 f"{v.get('evidence')}) but no fault was injected into it"))
    # -- alerts ------------------------------------------------------------------------------
    # a residual alert that names a fault (a sensor bias, inconsistent estimates) accuses
    # an agent: one a fault was injected into by then (an "unexplained" one says that the
    # alarms fit no rule, and names the strongest alarm's agent for the operator to look at)
    for alert in summary.get("residual_alerts", []):
        if alert.get("fault") == "unexplained":
            continue
        if not any(f.agent == alert["agent"] and f.step <= alert["step"] for f in c.faults):
            out.append(Violation("alerts", alert["step"],
                                 f"residual alert on agent {alert['agent']} ({alert['fault']}"
                                 f", level {alert.get('score')}) but no fault was injected "
                                 f"into it by step {alert['step']}"))
    return out


def live_chaos(args, say) -> tuple:
    """``socmon chaos``: a live run under the fault schedule drawn from ``args.seed``,
    checked against the invariants; the run folder gets ``schedule.json``,
    ``invariants.json`` and the timeline besides ``up``'s files. Returns ``(report,
    status)``: status 1 when the run failed or broke an invariant, 130 interrupted
    (:func:`agent.run.setup.exit_status`)."""
    import argparse
    import dataclasses
    import json
    import time
    from pathlib import Path

    from agent.protocol.timing import DEFAULT as TIMING
    from agent.run.folder import write_atomic
    from agent.run.inputs import InputError
    from agent.run.jsonable import SCHEMA_VERSION, to_jsonable
    from agent.run.setup import exit_status, run_config
    from agent.run.summary import run_and_summarize, write_run_folder

    check_schedule_flags(args)
    kinds = tuple(k.strip() for k in args.faults.split(",") if k.strip())
    bad = [k for k in kinds if k not in CHAOS_KINDS]
    if bad or not kinds:
        raise InputError(f"--faults: unknown kinds {bad} (known: {', '.join(CHAOS_KINDS)})"
                           if bad else "--faults: give at least one kind")

    out = args.out or str(Path("runs") / f"chaos-{Path(args.scenario).stem}-s{args.seed}-"
                                          f"{time.strftime('%Y%m%d-%H%M%S')}")
    up_args = argparse.Namespace(
        scenario=args.scenario, steps=args.duration, gains=args.gains, seed=args.seed,
        out=out, delays=args.delays, step_ms=args.step_ms, deadline_ms=None,
        start_timeout=TIMING.start_timeout_s, quiet=args.quiet, no_monitor=False, monitors=2, drop=0.0,
        kill=[], stop=[],
        kill_monitor=None, hang_timeout=args.hang_timeout,
        hang_timeout_max=TIMING.hang_timeout_max_s, check_simulator=False,
        overwrite=args.overwrite)
    config = run_config(up_args, say, prog="chaos")
    schedule = draw_schedule(config.scenario, args.seed, args.duration, kinds, args.rate,
                             config.step_ms)
    config = dataclasses.replace(config, faults=tuple(schedule))
    write_atomic(config.out / "schedule.json",
                 json.dumps([f.to_dict() for f in schedule], indent=2) + "\n")
    say(f"{len(schedule)} faults" + (": " if schedule else " drawn") + ", ".join(
        f"{f.kind}{' ' + str(f.agent) if f.agent else ''}@{f.step}" for f in schedule))
    s = config.scenario
    rec, summary, steps, mse, predicted = run_and_summarize(config, say)
    status = exit_status(rec, summary)          # writes the summary's error, as up's
    violations = [] if rec.failure else check_invariants(config, rec, summary, steps, mse)
    write_run_folder(config.out, summary, steps, mse, predicted, recording=rec, n=s.n)
    reached = steps[-1] if len(steps) else -1
    report = {
        "schema_version": SCHEMA_VERSION,
        "scenario": s.name, "seed": args.seed, "duration": args.duration,
        "faults": [f.to_dict() for f in schedule],
        # the run's last step, and the faults due by then (an interrupted or failed run
        # stops short of its schedule; its invariants are not checked)
        "reached": reached,
        "injected": sum(f.step <= reached for f in schedule),
        "diverged_at": summary.get("diverged_at"),     # a negative result beside them
        "failures": summary.get("failures", []),
        "rosters": summary.get("rosters", []),
        "violations": [v.to_dict() for v in violations],
        "no_verdict_due": summary.get("no_verdict_due", []),
        "error": rec.failure,
        "replay": f"socmon chaos {args.scenario} --seed {args.seed} --duration "
                  f"{args.duration} --faults {','.join(kinds)} --rate {args.rate:g}",
        "out": str(config.out),
    }
    write_atomic(config.out / "invariants.json",
                 json.dumps(to_jsonable(report), indent=2) + "\n")
    write_timeline(config.out, summary, steps, mse, schedule, rec.rosters)
    return report, status or (1 if violations else 0)


def write_timeline(out, summary, steps, mse, schedule, rosters) -> None:
    """timeline.json and timeline.png of a chaos run: faults, verdicts, activations, MSE."""
    import json

    import numpy as np

    from agent.run.folder import write_atomic
    from agent.run.jsonable import to_jsonable

    items = [{"step": f.step, "what": "fault", **f.to_dict()} for f in schedule]
    for v in summary.get("failures", []):
        # a failure no verdict answered (a standby killed, no monitor alive) has no
        # detected_step: it is placed where the agent died, when that is known
        step = v.get("detected_step")
        what = "verdict" if step is not None else "undetected"
        step = step if step is not None else v.get("died_step")
        if step is not None:
            items.append({"step": step, "what": what, "agent": v["agent"],
                          "cause": v["cause"]})
    items += [{"step": at, "what": "activation", "ids": list(ids), "epoch": ep}
              for at, ids, ep in rosters[1:]]
    items.sort(key=lambda x: x["step"])
    write_atomic(out / "timeline.json", json.dumps(to_jsonable(items), indent=2) + "\n")
    from agent.run.summary import plottable, pyplot, running_mean, smoothing_window

    plt = pyplot()
    if plt is None:
        return
    ok = plottable(mse)
    mse = np.asarray(mse, dtype=float)
    fig, (ax, lane) = plt.subplots(2, 1, figsize=(10.5, 5), sharex=True,
                                   gridspec_kw={"height_ratios": [3, 1.4]})
    window = smoothing_window(len(mse))
    ax.semilogy(np.asarray(steps)[ok], mse[ok], lw=0.6 if window > 1 else 0.8,
                color="tab:blue", alpha=0.3 if window > 1 else 1.0)
    if window > 1:
        ax.semilogy(np.asarray(steps), running_mean(mse, window), lw=1.3, color="tab:blue")
    ax.set_ylabel("MSE")
    ax.set_title(f"{summary['scenario']}: chaos, seed {summary['seed']}")
    M = summary["agents"] + summary["standby"]
    colours = {"kill": "tab:red", "stop": "tab:orange", "partition": "tab:purple",
               "delay": "tab:brown", "drop": "tab:olive", "monitor": "k", "crash": "tab:red",
               "hang": "tab:pink", "sensor": "tab:cyan", "lie": "darkred", "bias": "gold"}
    last = steps[-1] if len(steps) else 0
    for f in schedule:
        y = f.agent if f.agent else 0
        if f.kind in WRONG_KINDS:             # from its step to the run's end
            width = max(1.0, last - f.step)
        else:
            width = max(1.0, f.seconds * 1000.0 / summary["step_ms"]) if f.seconds else 3
        lane.barh(y, width, left=f.step, height=0.6, color=colours.get(f.kind, "grey"),
                  alpha=0.8)
        lane.text(f.step, y + 0.35, f.kind, fontsize=7)
        ax.axvline(f.step, color=colours.get(f.kind, "grey"), lw=0.6, alpha=0.6)
    for v in summary.get("failures", []):
        if v.get("detected_step") is not None:      # no verdict: nothing to mark
            lane.plot(v["detected_step"], v["agent"], "kx", ms=6)
    for at, ids, _ in rosters[1:]:
        ax.axvline(at, color="tab:green", lw=0.8, ls="--")
        for a in ids:
            lane.plot(at, a, "g|", ms=10)
    lane.set_yticks(range(0, M + 1), ["monitor"] + [f"agent {a}" for a in range(1, M + 1)])
    lane.set_xlabel("step")
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    kinds = sorted({f.kind for f in schedule})
    lane.legend(handles=[Patch(color=colours.get(k, "grey"), alpha=0.8, label=f"fault: {k}")
                         for k in kinds]
                + [Line2D([], [], color="k", marker="x", ls="", label="verdict"),
                   Line2D([], [], color="g", marker="|", ls="", ms=10,
                          label="roles in force (activation)")],
                loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7, frameon=False)
    traces = [Line2D([], [], lw=0.6, alpha=0.3, label="MSE (live), each step"),
              Line2D([], [], lw=1.3, label=f"its mean over {window} steps")] \
        if window > 1 else [Line2D([], [], lw=0.8, label="MSE (live)")]
    ax.legend(handles=traces + [Line2D([], [], color="tab:green", lw=0.8, ls="--",
                                       label="a new configuration in force")],
              loc="upper right", fontsize=8)
    fig.tight_layout()
    try:
        fig.savefig(out / "timeline.png", dpi=110)
    finally:
        plt.close(fig)
