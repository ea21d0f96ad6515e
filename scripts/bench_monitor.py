"""Failure handling measured on live runs: detection, reassignment, recovery, false positives.

Runs ``socmon up`` repeatedly on this machine (world, agents, standby and monitor as
separate processes on loopback) and reads each run folder:

- crash: ``--kill STEP:1`` (agent 1 SIGKILLs itself at a logged wall time); detection =
  the monitor's verdict time minus that time;
- hang: ``--stop STEP:2:SECONDS`` (SIGSTOP by ``up`` at a logged time); detection = verdict
  minus SIGSTOP time;
- verdict -> every assignment confirmed (from the monitor's events file);
- steps from the failure until the MSE (mean of a 20-step window) is back within 2x of
  the exact prediction for the new configuration;
- false positives: verdicts in healthy runs, per 10,000 steps.

Usage: python scripts/bench_monitor.py [--scenario paper-14-live|sampson] [--repeats 3]
       [--healthy-steps 3000]
       python scripts/bench_monitor.py --recovery [--taus 3,7,15] [--busy 2]
           [--scenario ...]: every single failure and one double failure at each delay
           bound (15-step delays: ``--delays uniform:T``), with ``--busy`` busy loops beside
           the runs: detection step, verdict -> roles in force (steps, and ms from the
           verdict to every assignment confirmed), the gains used (precomputed or designed,
           fast or refined), peak MSE after the fault over the exact level after, steps
           above 2x, re-issues, recovered, divergence, and the simulator check.
       python scripts/bench_monitor.py --per-failure --taus 3,7,15 [--kill-step 150]
       python scripts/bench_monitor.py --sequential --taus 3 [--gap 8] [--busy 2]: agent 2
           killed, agent 1 --gap steps later (the second failure's gain designed on request)

``--per-failure``: for each delay bound T (``--delays uniform:T``) and every agent of the
initial configuration, one run with that agent killed (``--kill STEP:A``): detection (verdict
minus the logged SIGKILL time), verdict -> roles in force in steps (the step the new roles
took effect, read from the agents' statuses, minus the verdict's step) and in ms at the run's
step period, verdict -> every assignment confirmed in ms, re-issues, which gain went in
first (fast or refined, precomputed or not) and whether the refined one followed, and the
hold window (taubar + 17 steps) the switch must come inside. The machine's load average is
printed with the figures.

``sampson`` is the Sampson-like scenario of the paper's Section 5.2 built from
../shared/data/sampson (18 nodes, 4 agents) with A rescaled to rho(A) = 0.98 for long live
runs and one standby agent added.
"""

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


SCENARIO = "paper-14-live"


def sampson_live(tmp):
    """The Sampson-like scenario, rho(A) = 0.98, one standby, as a TOML file."""
    sys.path.insert(0, str(ROOT))
    from design.experiments import sampson_scenario
    from design.scenario import scenario_to_toml

    s = sampson_scenario(ROOT.parent / "shared" / "data" / "sampson" /
                         "sampson_samplike_edges.csv")
    s = s.replace(name="sampson-live", A=s.A * (0.98 / s.rho_A), standby=1)
    path = Path(tmp) / "sampson-live.toml"
    path.write_text(scenario_to_toml(s))
    return str(path)


def seven_agents(tmp):
    """Five communities, five agents and two standbys (seven agent processes): the run
    of the false-positive table, as a TOML file."""
    sys.path.insert(0, str(ROOT))
    from design.generate import communities_scenario
    from design.scenario import scenario_from_dict, scenario_to_toml

    s = scenario_from_dict(communities_scenario(5, seed=5), source="communities-5")
    s = s.replace(name="communities-5-live", standby=2)
    path = Path(tmp) / "communities-5-live.toml"
    path.write_text(scenario_to_toml(s))
    return str(path)


def false_positives(args, tmp):
    """Healthy runs of seven agents beside ``--busy`` loops: every verdict is false; with
    the re-issues and the period actually sustained (late and dropped estimates)."""
    scenario = seven_agents(tmp)
    print(f"{Path(scenario).stem}: 5 agents + 2 standbys, 20 ms steps, "
          f"{args.healthy_steps} healthy steps per run, {args.busy} busy loops, hang timeout "
          + ("fixed at 1 s" if args.fixed_timeout else "1 s growing with the statuses' pace"))
    print(f"{'run':>3} {'verdicts':>8} {'reissues':>8} {'epoch':>5} {'late':>6} "
          f"{'drops':>6} {'load':>5}  period")
    total_v = total_steps = 0
    for r in range(args.repeats):
        out = tmp / f"fp{r}"
        stop = busy_loops(args.busy)
        try:
            fixed = ("--hang-timeout-max", "1") if args.fixed_timeout else ()
            s = up(out, "--seed", str(r), *fixed, steps=args.healthy_steps,
                   scenario=scenario)
        finally:
            load = os.getloadavg()[0]
            stop()
        verdicts = [e for e in events(out) if e.get("kind") == "verdict"]
        total_v += len(verdicts)
        total_steps += s["steps"]
        sustained = not any("period not sustained" in w for w in s.get("warnings", []))
        print(f"{r:>3} {len(verdicts):>8} {len(s.get('reissues', [])):>8} "
              f"{max(x['epoch'] for x in s['rosters']):>5} "
              f"{s['late']:>6} {s['drops']:>6} {load:>5.1f}  "
              f"{'sustained' if sustained else 'NOT sustained'}"
              + "".join(f"\n      verdict: agent {v['agent']} {v['cause']} ({v['evidence']})"
                        for v in verdicts))
    print(f"false convictions: {total_v} in {total_steps} healthy steps "
          f"({1e4 * total_v / max(total_steps, 1):.2f} per 10,000 steps)")
    print(f"run folders: {tmp}")


def up(out, *flags, steps=400, scenario=None):
    scenario = scenario or SCENARIO
    cmd = [sys.executable, "-m", "agent.cli", "up", scenario, "--steps", str(steps), "--out",
           str(out), "--json", "--quiet", *flags]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=900)
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited {p.returncode}: {p.stderr[-2000:]}")
    return json.loads(p.stdout)


def events(out):
    return [json.loads(line) for line in (Path(out) / "events.jsonl").read_text().splitlines()]


def recovery_steps(out, summary):
    import csv

    rows = list(csv.reader(open(Path(out) / "mse.csv")))[1:]
    mse = {int(k): float(m) for k, m in rows}
    pred = summary.get("mse_steady_exact_after_recovery")
    f = summary["failures"][0]
    start = f["detected_step"]
    for k in range(f["activate_at"], max(mse) - 20):
        window = [mse[j] for j in range(k, k + 20)]
        if statistics.mean(window) <= 2 * pred:
            return k - start
    return None


def busy_loops(count):
    """``count`` processes spinning on a core each (the load a run meets beside others)."""
    import os
    import signal

    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"],
                              start_new_session=True) for _ in range(count)]

    def stop():
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            p.wait()
    return stop


def recovery_row(out, s, killed):
    """What one run with ``--kill 150:AGENTS`` did, read from its run folder."""
    import csv
    import math

    rows = list(csv.reader(open(Path(out) / "mse.csv")))[1:]
    mse = {int(k): float(m) for k, m in rows}
    f = s["failures"]
    ev = events(out)
    v = [e for e in ev if e["kind"] == "verdict"]
    c = next((e for e in ev if e["kind"] == "confirmed"), None)
    exact = s.get("mse_steady_exact_after_recovery")
    first = min(x["detected_step"] for x in f) if f else None
    after = [m for k, m in mse.items() if first is not None and k >= first]
    peak = max(after) if after else float("nan")
    above = sum(1 for m in after if exact and m > 2 * exact)
    switch = [x["activate_at"] - x["detected_step"] for x in f
              if x.get("activate_at") is not None]
    return {
        "killed": killed, "detected": [x["detected_step"] for x in f],
        "switch_steps": max(switch) if switch else None,
        "confirm_ms": 1e3 * (c["t"] - v[0]["detected_t"]) if c and v else None,
        "precomputed": all(x.get("precomputed") for x in f) if f else None,
        "gains": sorted({x.get("gains") or "?" for x in f}),
        "peak_over_exact": peak / exact if exact and math.isfinite(exact) else None,
        "steps_above_2x": above, "reissues": len(s.get("reissues", [])),
        "recovered": s.get("recovered"), "diverged_at": s.get("diverged_at"),
        "check": s.get("max_rel_diff_vs_simulator"),
    }


def recovery_table(args, tmp):
    stop = busy_loops(args.busy)
    try:
        table = []
        for tau in [int(t) for t in args.taus.split(",")]:
            for killed in ("1", "2", "3", "1,2"):
                out = tmp / f"T{tau}-k{killed.replace(',', '')}"
                try:
                    s = up(out, "--delays", f"uniform:{tau}", "--kill", f"150:{killed}",
                           "--check-simulator", steps=450)
                except RuntimeError as exc:       # a failed check exits 1: still read it
                    s = json.loads((out / "summary.json").read_text())
                    print(f"note: T={tau} kill {killed}: {str(exc)[:200]}", file=sys.stderr)
                row = recovery_row(out, s, killed)
                row["tau"] = tau
                table.append(row)
                print(json.dumps(row), flush=True)
    finally:
        stop()
    print(f"\n{args.scenario}, 20 ms steps, kill at step 150 of 450, {args.busy} busy loops")
    print("T   killed  switch(steps)  confirmed(ms)  gains            peak/exact  >2x  "
          "reissues  recovered  diverged  check")
    for r in table:
        peak = "-" if r["peak_over_exact"] is None else f"{r['peak_over_exact']:.2f}"
        conf = "-" if r["confirm_ms"] is None else f"{r['confirm_ms']:.0f}"
        gains = ("precomputed " if r["precomputed"] else "designed ") + "/".join(r["gains"])
        print(f"{r['tau']:<3} {r['killed']:<7} {str(r['switch_steps']):>13}  {conf:>13}  "
              f"{gains:<16} {peak:>10}  {r['steps_above_2x']:>3}  {r['reissues']:>8}  "
              f"{str(r['recovered']):>9}  {str(r['diverged_at']):>8}  {_figure(r['check'])}")
    print(f"run folders: {tmp}")


def _figure(value) -> str:
    """A number as ``.2g``; what is not a number (``inf`` read back from JSON as a string,
    None) as it is."""
    return f"{value:.2g}" if isinstance(value, (int, float)) else str(value)
STEP_S = 0.02           # socmon up's default step period


def per_failure(tmp, taus, kill_step, steps, busy=0, no_precompute=False):
    """One run per (T, agent killed): the switch measured against the hold window, beside
    ``busy`` loops; with ``no_precompute`` every failure is unforeseen (``up
    --no-precompute``): its first gain is designed on request, and the gain wait (verdict
    -> the gains sent) measures the urgent design path."""
    import os

    sys.path.insert(0, str(ROOT))
    from design.scenario import load_scenario

    scen = load_scenario(SCENARIO)
    agents = list(range(1, len(scen.measure) + 1))
    print(f"{SCENARIO}, 20 ms steps, kill at step {kill_step}, one run per (T, agent), "
          f"{busy} busy loops{', no precompute' if no_precompute else ''}; "
          f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}", flush=True)
    print(f"{'T':>3} {'agent':>5} {'detect ms':>9} {'v->force steps':>14} {'ms':>6} "
          f"{'hold':>4} {'gain wait ms':>12} {'v->confirmed ms':>15} {'reissues':>8} "
          f"{'first gain':>18} {'refined epoch':>13} {'load':>5}", flush=True)
    rows = []
    for tau in taus:
        for a in agents:
            out = tmp / f"T{tau}-kill{a}"
            stop = busy_loops(busy)
            try:
                s = up(out, "--kill", f"{kill_step}:{a}", "--delays", f"uniform:{tau}",
                       "--seed", str(a), *(["--no-precompute"] if no_precompute else []),
                       steps=steps)
            except RuntimeError as e:
                print(f"{tau:3} {a:5} run failed: {str(e)[-300:]}", flush=True)
                rows.append({"T": tau, "agent": a, "error": str(e)[-300:]})
                continue
            finally:
                load = os.getloadavg()[0]
                stop()
            log = (out / "logs" / f"agent-{a}.log").read_text()
            m = re.search(r"SIGKILL at t=([0-9.]+)", log)
            ev = events(out)
            v = next((e for e in ev if e["kind"] == "verdict" and e["agent"] == a), None)
            f = next((x for x in s["failures"] if x["agent"] == a), None)
            r = next((e for e in ev if e["kind"] == "reassign" and a in e.get("failed", [])),
                     None)
            later = [e for e in ev if e["kind"] == "reassign" and r is not None
                     and e["epoch"] > r["epoch"] and e.get("gains") == "refined"
                     and not e.get("failed")]
            c = next((e for e in ev if e["kind"] == "confirmed" and v is not None
                      and e["t"] >= v["detected_t"]), None)
            row = {"T": tau, "agent": a, "hold_steps": tau + 17,
                   "detect_ms": (1e3 * (v["detected_t"] - float(m.group(1)))
                                 if v and m else None),
                   "force_steps": (f["activate_at"] - f["detected_step"]
                                   if f and f.get("activate_at") is not None else None),
                   "confirm_ms": 1e3 * (c["t"] - v["detected_t"]) if c and v else None,
                   "gain_wait_ms": (1e3 * (r["mono_sent"] - r["mono"])
                                    if r and "mono_sent" in r else None),
                   "load": load,
                   "reissues": len(s.get("reissues", [])),
                   "first_gain": (f"{r.get('gains')}{' pre' if r.get('precomputed') else ''}"
                                  + (f" {r['gains_rho']:.3f}" if r.get("gains_rho") is not None
                                     else f" <{r['gains_rho_below']:g}"
                                     if r.get("gains_rho_below") is not None else " ?")
                                  if r else None),
                   "refined_epoch": later[0]["epoch"] if later else None,
                   "recovered": s.get("recovered")}
            rows.append(row)
            fs = row["force_steps"]
            print(f"{tau:3} {a:5} {_fmt(row['detect_ms']):>9} {_fmt(fs):>14} "
                  f"{_fmt(fs * STEP_S * 1e3 if fs is not None else None):>6} {tau + 17:4} "
                  f"{_fmt(row['gain_wait_ms']):>12} {_fmt(row['confirm_ms']):>15} "
                  f"{row['reissues']:8} {row['first_gain'] or '-':>18} "
                  f"{_fmt(row['refined_epoch']):>13} {load:5.1f}", flush=True)
    waits = [r["gain_wait_ms"] for r in rows if r.get("gain_wait_ms") is not None]
    if waits:
        print(f"verdict -> first gain sent: median {statistics.median(waits):.0f} ms, max "
              f"{max(waits):.0f} ms over {len(waits)} runs; within 1 s: "
              f"{sum(w <= 1000 for w in waits)} of {len(waits)}")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print(f"run folders: {tmp}")
    (tmp / "per_failure.json").write_text(json.dumps(rows, indent=1))
    return rows


def _fmt(x):
    if x is None:
        return "-"
    return f"{x:.0f}" if isinstance(x, float) else str(x)


def sequential(args, tmp, taus):
    """Two kills a few steps apart (agent 2, then agent 1 ``--gap`` steps later), beside
    ``--busy`` loops: the second failure comes before the precompute for the configuration
    that answered the first is done, so its first gain is designed on request (the urgent
    process). Per run: the wait for that gain (the reassignment's ``mono_sent`` minus its
    ``mono``), verdict -> roles in force in steps, re-issues, recovered, the simulator's
    replay."""
    print(f"{SCENARIO}, 20 ms steps, kill 2 at step {args.kill_step} and 1 at "
          f"{args.kill_step + args.gap}, {args.busy} busy loops, {args.repeats} runs per T",
          flush=True)
    print(f"{'T':>3} {'run':>3} {'2nd: pre':>8} {'gain wait ms':>12} {'v->force steps':>14} "
          f"{'reissues':>8} {'recovered':>9} {'sim diff':>9} {'load':>5}", flush=True)
    waits = []
    for tau in taus:
        for r in range(args.repeats):
            out = tmp / f"seq-T{tau}-{r}"
            stop = busy_loops(args.busy)
            try:
                s = up(out, "--kill", f"{args.kill_step}:2", "--kill",
                       f"{args.kill_step + args.gap}:1", "--delays", f"uniform:{tau}",
                       "--check-simulator", "--seed", str(r), steps=args.steps)
            except RuntimeError as e:
                print(f"{tau:3} {r:3} run failed: {str(e)[-300:]}", flush=True)
                continue
            finally:
                load = os.getloadavg()[0]
                stop()
            reassigns = [e for e in events(out) if e["kind"] == "reassign" and e.get("failed")]
            second = next((e for e in reassigns if 1 in e["failed"]), None)
            f = next((x for x in s["failures"] if x["agent"] == 1), {})
            wait = (1e3 * (second["mono_sent"] - second["mono"])
                    if second and "mono_sent" in second else None)
            if wait is not None and not second.get("precomputed"):
                waits.append(wait)
            force = (f["activate_at"] - f["detected_step"]
                     if f.get("activate_at") is not None and f.get("detected_step") is not None
                     else None)
            print(f"{tau:3} {r:3} {str(second.get('precomputed')) if second else '-':>8} "
                  f"{'-' if wait is None else f'{wait:.0f}':>12} "
                  f"{'-' if force is None else force:>14} {len(s.get('reissues', [])):>8} "
                  f"{str(s.get('recovered')):>9} "
                  f"{s.get('max_rel_diff_vs_simulator', float('nan')):>9.1e} {load:>5.1f}",
                  flush=True)
    if waits:
        print(f"first gain designed on request: median {statistics.median(waits):.0f} ms, "
              f"max {max(waits):.0f} ms over {len(waits)} runs")
    print(f"run folders: {tmp}")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="paper-14-live", choices=("paper-14-live", "sampson"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--healthy-steps", type=int, default=3000)
    ap.add_argument("--recovery", action="store_true",
                    help="the recovery table (every single failure and one double failure)")
    ap.add_argument("--busy", type=int, default=0,
                    help="busy loops beside the --recovery and --false-positives runs")
    ap.add_argument("--false-positives", action="store_true",
                    help="healthy runs of 5 agents + 2 standbys: verdicts, re-issues, load")
    ap.add_argument("--fixed-timeout", action="store_true",
                    help="--false-positives with the hang timeout fixed at 1 s (the "
                         "comparison: not grown with the statuses' pace)")
    ap.add_argument("--per-failure", action="store_true",
                    help="every single failure at each --taus delay bound")
    ap.add_argument("--taus", default="3,7,15",
                    help="delay bounds T for --per-failure and --recovery")
    ap.add_argument("--kill-step", type=int, default=150)
    ap.add_argument("--steps", type=int, default=400, help="steps of a --per-failure run")
    ap.add_argument("--sequential", action="store_true",
                    help="two kills --gap steps apart: the second one's gain designed on "
                         "request")
    ap.add_argument("--gap", type=int, default=8, help="steps between the --sequential kills")
    ap.add_argument("--no-precompute", action="store_true",
                    help="--per-failure runs with up --no-precompute: every failure is "
                         "unforeseen, its first gain designed on request")
    args = ap.parse_args()
    try:
        taus = [int(t) for t in args.taus.split(",")]
    except ValueError:
        ap.error(f"--taus: comma-separated integers expected, got {args.taus!r}")
    tmp = Path(tempfile.mkdtemp(prefix="bench-monitor-"))
    global SCENARIO
    SCENARIO = sampson_live(tmp) if args.scenario == "sampson" else args.scenario
    if args.recovery:
        return recovery_table(args, tmp)
    if args.false_positives:
        return false_positives(args, tmp)
    if args.no_precompute and not args.per_failure:
        ap.error("--no-precompute: only with --per-failure")
    if args.per_failure:
        per_failure(tmp, taus, args.kill_step, args.steps, args.busy, args.no_precompute)
        return
    if args.sequential:
        return sequential(args, tmp, taus)
    rows = {"crash": [], "hang": []}
    for r in range(args.repeats):
        out = tmp / f"crash{r}"
        s = up(out, "--kill", "150:1", "--seed", str(r))
        log = (out / "logs" / "agent-1.log").read_text()
        t_kill = float(re.search(r"SIGKILL at t=([0-9.]+)", log).group(1))
        ev = events(out)
        v = next(e for e in ev if e["kind"] == "verdict")
        c = next((e for e in ev if e["kind"] == "confirmed"), None)
        rows["crash"].append({"detect_ms": 1e3 * (v["detected_t"] - t_kill),
                              "confirm_ms": 1e3 * (c["t"] - v["detected_t"]) if c else None,
                              "precomputed": s["failures"][0].get("precomputed"),
                              "recovery_steps": recovery_steps(out, s)})
        out = tmp / f"hang{r}"
        s = up(out, "--stop", "150:2:3", "--seed", str(r), steps=500)
        ev = events(out)
        v = next(e for e in ev if e["kind"] == "verdict")
        c = next((e for e in ev if e["kind"] == "confirmed"), None)
        t_stop = next(e["t"] for e in s["events"] if e.get("signal") == "SIGSTOP")
        rows["hang"].append({"detect_ms": 1e3 * (v["detected_t"] - t_stop),
                             "confirm_ms": 1e3 * (c["t"] - v["detected_t"]) if c else None,
                             "cause": v["cause"], "recovery_steps": recovery_steps(out, s)})
    out = tmp / "healthy"
    s = up(out, steps=args.healthy_steps)
    fp = len(s["failures"])
    print(f"{args.scenario}, 20 ms steps, {args.repeats} runs per fault, on this machine")
    print(f"{'fault':6} {'detect ms median/worst':>24} {'verdict->confirmed ms':>24} "
          f"{'steps to 2x predicted':>22}")
    for name, rs in rows.items():
        d = [x["detect_ms"] for x in rs if x["detect_ms"] is not None]
        c = [x["confirm_ms"] for x in rs if x["confirm_ms"] is not None]
        k = [x["recovery_steps"] for x in rs if x["recovery_steps"] is not None]
        print(f"{name:6} {statistics.median(d):11.1f} / {max(d):9.1f} "
              f"{(statistics.median(c) if c else float('nan')):11.1f} / "
              f"{(max(c) if c else float('nan')):9.1f} "
              f"{(statistics.median(k) if k else float('nan')):10} / {max(k) if k else '-'}")
    print(f"false positives: {fp} verdicts in {args.healthy_steps} healthy steps "
          f"({1e4 * fp / args.healthy_steps:.2f} per 10,000 steps)")
    print(f"run folders: {tmp}")


if __name__ == "__main__":
    main()
