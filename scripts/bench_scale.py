"""Scale of a live run on this machine: N agents as N processes, peer mesh vs one router.

For each N of ``--sizes`` the scenario is ``communities-N`` (:mod:`design.generate`; the
built-ins for 16 and 32, generated for other N), its gain designed once
(``socmon design --target 0.97``). Then for each transport (the peer mesh, and
``socmon up --router``) ``socmon up`` runs ``--steps`` steps at each period of
``--step-ms`` in turn, fastest first, until one is *sustained*: every step reached, no
estimate dropped or late (the agents wait one step for their neighbours), no sensor
reading missed. The runs have no monitor (its precomputation for 32 agents would dominate
the start-up) and no link delays.

Figures per run: the sustained steps/s (1000 / the smallest sustained period), the share of
neighbour estimates not there by the deadline (missed: dropped, or late) at each period, the agent-to-agent hop (publish -> decoded in
the receiving agent; median of the agents' medians, worst p99), CPU per agent (ms of CPU a
step, mean over agents, and % of one core) and the router's CPU (% of one core), both from
the clock's start to the process's exit (the start-up, read from /proc when the world's
clock starts, is left out), the world's, the monitors' and the recorder's (``up``
itself) CPU the same way, each process's peak resident memory (VmHWM, read twice a
second), the machine's 1-minute load average at the run's start and the highest over its
steps (the run's own processes count in it), and the links
the transport holds: (P-1)P/2 for P processes in the mesh (N agents, world, recorder), P
through the router.

``--baseline DIR``: each run is also made with the code of the tree DIR (a checkout of an
earlier commit), right after this tree's, at the same period: before and after in one
run, under the same load. ``--monitor``: the runs have the monitor (and its precompute).
``--scenario NAME``: that scenario instead of ``communities-N`` (``--sizes`` is then its
agent count; ``paper-14-live``: the hop target's case). ``--raw-rtt``: beside each run,
two bare zenoh-python peers ping once a step (``scripts/raw_rtt.py``): the raw round trip
over the run's steps (from the world's clock start, as the hop), and the hop's median
over it.

Usage::

    python scripts/bench_scale.py [--sizes 4,16,32] [--steps 1000] [--step-ms 10,20,40]
                                  [--transports peer,router] [--baseline DIR] [--monitor]
                                  [--scenario NAME] [--raw-rtt]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def socmon(*argv, timeout):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "agent.cli", *argv], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout,
                          start_new_session=True)


def scenario_for(N: int, folder: Path) -> str:
    from design.generate import communities_scenario
    from design.scenario import builtin_scenarios, scenario_from_dict, scenario_to_toml

    name = f"communities-{N}"
    if name in builtin_scenarios():
        return name
    path = folder / f"{name}.toml"
    path.write_text(scenario_to_toml(scenario_from_dict(communities_scenario(N, seed=N))))
    return str(path)


def _cpu_s(pid: int, tree: bool = False):
    """CPU seconds (user + system) of a live process so far, None once it is gone. With
    ``tree``, also of its children it has reaped and its live descendants (a monitor's
    gain workers): what ``wait4`` gives once the whole tree is reaped, so that the
    difference with it covers the steps alone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    total = sum(int(f) for f in fields[11:15 if tree else 13]) / os.sysconf("SC_CLK_TCK")
    for task in Path(f"/proc/{pid}/task").glob("*/children") if tree else ():
        try:
            children = task.read_text().split()
        except OSError:
            continue
        total += sum(_cpu_s(int(child), tree=True) or 0.0 for child in children)
    return total


def _peak_rss_mib(pid: int):
    """The peak resident memory (VmHWM) of a live process in MiB, None once it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        return None
    return None


class RunSampler:
    """Beside a run, twice a second: each process's peak resident memory (VmHWM, the last
    value read before it exited) and the machine's 1-minute load average (the highest seen
    over the steps: the run's own processes count in it)."""

    def __init__(self):
        import threading

        self.pids, self.peak_mib, self.load_max = {}, {}, None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, daemon=True)

    def __enter__(self):
        self._thread.start()
        return self

    def _loop(self):
        while not self._stop.wait(0.5):
            for name, pid in list(self.pids.items()):
                mib = _peak_rss_mib(pid)
                if mib is not None:
                    self.peak_mib[name] = mib
            if self.pids:
                load = os.getloadavg()[0]
                self.load_max = load if self.load_max is None else max(self.load_max, load)

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        return False


def run_up(scenario, gains, steps, step_ms, out, router, root=ROOT, monitor=False,
           extra=()) -> dict:
    """``socmon up``'s summary (the code of the tree ``root``), with
    ``cpu_at_clock_start``: the CPU each process (and ``up`` itself, the recorder) had
    spent when the world's clock started (start-up: imports, session, gains, the
    monitor's precompute until then), read from /proc, so that the CPU of the steps alone
    can be told apart; ``cpu_s["recorder"]``: ``up``'s CPU at its end; ``peak_mib``: each
    process's peak resident memory; ``load_max``: the highest 1-minute load average
    over the steps."""
    argv = ["up", scenario, "--steps", str(steps), "--step-ms", str(step_ms), "--gains",
            str(gains), "--out", str(out), "--delays", "none", "--json",
            "--quiet", "--start-timeout", "300", *([] if monitor else ["--no-monitor"]),
            *extra]
    env = dict(os.environ, PYTHONPATH=str(root))
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", *argv,
                             *(["--router"] if router else [])], cwd=root, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    at_start, clock_start, recorder_cpu = {}, None, None
    sampler = RunSampler()
    try:
        deadline = time.monotonic() + 900
        world_log = out / "logs" / "world.log"
        with sampler:
            sampler.pids["recorder"] = proc.pid
            while proc.poll() is None and time.monotonic() < deadline:
                try:
                    started = "clock starts" in world_log.read_text()
                    pids = json.loads((out / "run.json").read_text())["processes"]
                except (OSError, ValueError, KeyError):
                    started = False
                if started:
                    at_start = {name: _cpu_s(p["pid"], tree=True) for name, p in pids.items()
                                if p.get("pid")}
                    at_start["recorder"] = _cpu_s(proc.pid)
                    sampler.pids.update({name: p["pid"] for name, p in pids.items()
                                         if p.get("pid")})
                    clock_start = time.time()
                    break
                time.sleep(0.05)
            # up's own CPU just before it exits (it writes the folder last): read while it
            # lives, as the children's come from its summary
            while proc.poll() is None and time.monotonic() < deadline + steps * step_ms / 1e3:
                cpu = _cpu_s(proc.pid)
                recorder_cpu = cpu if cpu is not None else recorder_cpu
                if clock_start is not None and time.time() > clock_start + steps * step_ms / 1e3:
                    break
                time.sleep(0.1)
            stdout, stderr = proc.communicate(timeout=900 + steps * step_ms / 1000 * 5)
        # the steps: from the world's clock start to the run's last step (its span at the
        # period; what follows is the run folder being written)
        steps_window = (None if clock_start is None
                        else (clock_start, min(time.time(), clock_start + steps * step_ms / 1e3)))
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    try:
        summary = json.loads(stdout)
    except ValueError:
        raise RuntimeError(f"up exited with {proc.returncode} and no summary: "
                           f"{' '.join(stderr.split())[-400:]}") from None
    summary["cpu_at_clock_start"] = at_start
    summary["cpu_s"]["recorder"] = recorder_cpu
    summary["steps_window"] = steps_window
    summary["peak_mib"] = sampler.peak_mib
    summary["load_max"] = sampler.load_max
    return summary


class RawRoundTrip:
    """``scripts/raw_rtt.py``'s pong and ping beside a run (``with``): one ping a step
    period; :attr:`result` once the block ends (median and p99 in ms, or None)."""

    def __init__(self, step_ms: float, out: Path):
        self.step_ms, self.out, self.result = step_ms, out, None

    def __enter__(self):
        from broker_free_net.ports import listen_port

        endpoint = f"tcp/127.0.0.1:{listen_port()}"
        script = str(ROOT / "scripts" / "raw_rtt.py")
        self.procs = [subprocess.Popen([sys.executable, script, "pong", "--listen", endpoint],
                                       start_new_session=True)]
        try:
            self.procs.append(subprocess.Popen(
                [sys.executable, script, "ping", "--connect", endpoint, "--period-ms",
                 str(self.step_ms), "--out", str(self.out)], start_new_session=True))
        except OSError:
            self.__exit__(None, None, None)
            raise
        return self

    def over(self, window):
        """Median and p99 (ms) of the round trips sent within ``window`` (wall-clock
        ``(start, end)``: the run's steps), and how many; None without any."""
        if not self.result or window is None:
            return None
        rtts = sorted(r for t, r in self.result.get("samples", []) if window[0] <= t <= window[1])
        if not rtts:
            return None
        return {"median_ms": 1e3 * statistics.median(rtts),
                "p99_ms": 1e3 * rtts[int(0.99 * (len(rtts) - 1))], "n": len(rtts),
                "lost": self.result.get("lost")}

    def __exit__(self, *exc):
        for p in reversed(self.procs):          # the ping first: it writes its figures
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        try:
            self.result = json.loads(self.out.read_text())
        except (OSError, ValueError):
            self.result = None
        return False


def describe(summary: dict, N: int, steps: int, step_ms: float) -> dict:
    span = steps * step_ms / 1000.0
    hops = [h for h in summary.get("hop_ms", {}).values() if h]
    start = summary["cpu_at_clock_start"]
    stepping = {k: v - start[k] for k, v in summary["cpu_s"].items()
                if v is not None and start.get(k) is not None}
    agent_cpu = [v for k, v in stepping.items() if k.startswith("agent-")]
    received = max(1, N * steps)           # each agent waits for one neighbour a step
    return {
        "step_ms": step_ms,
        "sustained": (summary["drops"] == 0 and summary["late"] == 0
                      and summary["sensor_missed"] == 0 and summary["steps"] == steps
                      and "error" not in summary),
        "steps": summary["steps"], "late": summary["late"], "drops": summary["drops"],
        "late_share": summary["drops"] / received,
        "hop_median_ms": statistics.median(h["median"] for h in hops) if hops else None,
        "hop_p99_ms": max(h["p99"] for h in hops) if hops else None,
        "cpu_ms_per_step": 1e3 * statistics.mean(agent_cpu) / steps if agent_cpu else None,
        "cpu_percent_per_agent": 100.0 * statistics.mean(agent_cpu) / span if agent_cpu
        else None,
        "router_cpu_percent": (100.0 * stepping["router"] / span
                               if "router" in stepping else None),
        # the other processes, % of one core over the steps
        "world_cpu_percent": _percent(stepping, "world", span),
        # (trees before a8f0963 named them monitor and monitor.2: a --baseline may be one)
        "monitor_cpu_percent": _percent(stepping, "monitor-1", span, "monitor"),
        "monitor2_cpu_percent": _percent(stepping, "monitor-2", span, "monitor.2"),
        "recorder_cpu_percent": _percent(stepping, "recorder", span),
        "peak_mib": _memory(summary.get("peak_mib", {})),
        "load_max": summary.get("load_max"),
        "wall_s": summary["wall_s"],
        # estimates each agent received a step (its subscriptions: in-neighbours only, or
        # every agent before them), mean over agents
        "received_per_step": _received_per_step(summary, steps),
    }


def _percent(stepping: dict, name: str, span: float, old_name: str = ""):
    name = name if name in stepping else old_name
    return 100.0 * stepping[name] / span if name in stepping else None


def _memory(peak: dict) -> dict:
    """Peak resident memory (MiB): the agents' mean and largest, and each other process."""
    agents = [v for k, v in peak.items() if k.startswith("agent-")]
    out = {k: v for k, v in peak.items() if not k.startswith("agent-")}
    if agents:
        out["agent_mean"], out["agent_max"] = statistics.mean(agents), max(agents)
    return out


def _received_per_step(summary: dict, steps: int):
    got = [sum(e.get("received", {}).values())
           for e in summary.get("estimates_from", {}).values()]
    return statistics.mean(got) / max(1, steps) if got else None


def _ratio(a, b) -> str:
    return f"{a / b:.2f}x" if a is not None and b else "-"


def fmt(value, spec):
    return "-" if value is None else format(value, spec)


def _share(row: dict, N: int) -> float:
    """Estimates not there by the deadline over those the agents waited for (one neighbour
    a step). An agent counts such an estimate in ``drops``, and in ``late`` too if it came
    after all, so ``drops`` is the count."""
    return row["drops"] / max(1, N * row["steps"])


def _others(row: dict) -> str:
    """World / monitor(s) / recorder CPU, % of one core over the steps."""
    mon = fmt(row.get("monitor_cpu_percent"), ".0f")
    if row.get("monitor2_cpu_percent") is not None:
        mon += "+" + fmt(row["monitor2_cpu_percent"], ".0f")
    return (f"{fmt(row.get('world_cpu_percent'), '.0f')} / {mon} / "
            f"{fmt(row.get('recorder_cpu_percent'), '.0f')}")


def _mib(row: dict) -> str:
    """Peak resident memory: agent mean (largest) / router / monitor / recorder, MiB."""
    m = row.get("peak_mib") or {}
    return (f"{fmt(m.get('agent_mean'), '.0f')} ({fmt(m.get('agent_max'), '.0f')}) / "
            f"{fmt(m.get('router'), '.0f')} / {fmt(m.get('monitor-1', m.get('monitor')), '.0f')} / "
            f"{fmt(m.get('recorder'), '.0f')}")


def print_table(results: list, periods: list) -> None:
    """The README's table: one row per N and transport."""
    cols = " | ".join(f"{p:g} ms" for p in periods)
    print(f"| N | transport | links | steps/s sustained | estimates missed at {cols} | "
          f"hop median / p99 (ms) | agent CPU ms/step (% core) | router CPU (% core) | "
          f"world / monitors / recorder CPU (% core) | peak MiB: agent mean (max) / router "
          f"/ monitor / recorder | load (1-min, start / max) |")
    print("| --- | --- | --- | --- | " + " | ".join("---" for _ in periods)
          + " | --- | --- | --- | --- | --- | --- |")
    steps = max(x["steps"] for r in results for x in r["runs"])
    for r in results:
        if not r["runs"]:
            print(f"| {r['N']} | {r['transport']} | {r['links']} | every run failed |")
            continue
        by_period = {x["step_ms"]: x for x in r["runs"]}
        best = next((x for x in r["runs"] if x["sustained"]), r["runs"][-1])
        sps = r["sustained_steps_per_s"]
        sustained = f"{sps:g}" if sps else f"< {1000 / periods[-1]:g}"
        shares = " | ".join(
            (f"{_share(by_period[p], r['N']):.1%}"
             + (f" (to step {by_period[p]['steps']})"
                if by_period[p]["steps"] < steps else "")) if p in by_period else "-"
            for p in periods)
        label = "router" if r["transport"] == "router" else "peer mesh"
        if r.get("tree", "this") != "this":
            label += f" ({r['tree']})"
        print(f"| {r['N']} | {label} | "
              f"{r['links']} | {sustained} | {shares} | "
              f"{fmt(best['hop_median_ms'], '.2f')} / {fmt(best['hop_p99_ms'], '.1f')} | "
              f"{fmt(best['cpu_ms_per_step'], '.2f')} "
              f"({fmt(best['cpu_percent_per_agent'], '.0f')}) | "
              f"{fmt(best['router_cpu_percent'], '.0f')} | {_others(best)} | {_mib(best)} | "
              f"{fmt(best.get('load_average'), '.1f')} / {fmt(best.get('load_max'), '.1f')} |")
    print("(hop, CPU, memory and load at the sustained period, else at the slowest tried; "
          "'-': not run (a faster period was sustained) or failed; 'to step S': the run was "
          "recorded only to step S of the requested ones, see the README. CPU: from /proc, "
          "the process's CPU at its end minus at the world's clock start, over the steps' "
          "span; memory: VmHWM read twice a second; load: the 1-minute load average at the "
          "run's start and the highest over its steps, the run's own processes included)")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default="4,16,32")
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--step-ms", default="10,20,40")
    parser.add_argument("--transports", default="peer,router")
    parser.add_argument("--json", metavar="FILE", help="also write every run's figures here")
    parser.add_argument("--baseline", metavar="DIR", type=Path,
                        help="also run each case with the code of this tree (before/after)")
    parser.add_argument("--monitor", action="store_true",
                        help="run the monitor too (default: no monitor)")
    parser.add_argument("--up-arg", metavar="ARG", action="append", default=[],
                        help="one more argument to every socmon up (repeatable), e.g. "
                        "--up-arg=--monitors --up-arg=1")
    parser.add_argument("--scenario", metavar="NAME",
                        help="this scenario instead of communities-N for each of --sizes")
    parser.add_argument("--raw-rtt", action="store_true",
                        help="measure the raw zenoh round trip beside each run "
                             "(scripts/raw_rtt.py)")
    parser.add_argument("--table", metavar="FILE",
                        help="only print the table of a --json FILE written before")
    args = parser.parse_args(argv)
    if args.table:
        results = json.loads(Path(args.table).read_text())
        print_table(results, sorted({x["step_ms"] for r in results for x in r["runs"]}))
        return 0
    sizes = [int(x) for x in args.sizes.split(",")]
    if args.scenario:
        from design.scenario import load_scenario

        sizes = [load_scenario(args.scenario).N]
    periods = sorted(float(x) for x in args.step_ms.split(","))
    transports = args.transports.split(",")
    trees = [("this", ROOT)]
    if args.baseline is not None:
        if not (args.baseline / "agent" / "cli").is_dir():
            parser.error(f"--baseline: {args.baseline} is not a socmon tree (no agent/cli)")
        trees.append(("baseline", args.baseline.resolve()))
    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_"))
    print(f"machine: {os.cpu_count()} cores, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared with other work)",
          flush=True)
    results = []
    for N in sizes:
        scenario = args.scenario or scenario_for(N, tmp)
        gains = tmp / f"gains-{N}.npz"
        t = time.monotonic()
        proc = socmon("design", scenario, "--target", "0.97", "--out", str(gains), "--json",
                      timeout=1800)
        if proc.returncode != 0:
            raise RuntimeError(f"design of {scenario} failed: {proc.stderr[-2000:]}")
        rho = json.loads(proc.stdout)["rho_exact"]
        print(f"N = {N}: {scenario}, gain rho {rho:.3f} designed in "
              f"{time.monotonic() - t:.1f} s", flush=True)
        for transport, (tree, root) in [(t, tr) for t in transports for tr in trees]:
            router = transport == "router"
            P = N + 2
            links = P if router else P * (P - 1) // 2
            tried = []
            for step_ms in periods:
                out = tmp / f"run-{N}-{transport}-{tree}-{step_ms:g}"
                load = os.getloadavg()[0]
                probe = (RawRoundTrip(step_ms, tmp / f"{out.name}-raw-rtt.json") if args.raw_rtt
                         else contextlib.nullcontext())
                try:
                    with probe:
                        summary = run_up(scenario, gains, args.steps, step_ms, out, router,
                                         root, args.monitor, args.up_arg)
                    row = describe(summary, N, args.steps, step_ms)
                except RuntimeError as exc:
                    print(f"  {transport:6} {step_ms:4g} ms: failed: {exc}", flush=True)
                    continue
                row["load_average"] = load
                raw = probe.over(summary.get("steps_window")) if args.raw_rtt else None
                row["raw_rtt_median_ms"] = raw and raw.get("median_ms")
                row["raw_rtt_p99_ms"] = raw and raw.get("p99_ms")
                tried.append(row)
                print(f"  {transport:6} {tree:8} {step_ms:4g} ms: sustained "
                      f"{'yes' if row['sustained'] else 'no '}  missed {row['drops']} "
                      f"({row['late_share']:.2%}, {row['late']} came late)"
                      f"  hop {fmt(row['hop_median_ms'], '.2f')} / "
                      f"{fmt(row['hop_p99_ms'], '.1f')} ms  agent CPU "
                      f"{fmt(row['cpu_ms_per_step'], '.2f')} ms/step "
                      f"({fmt(row['cpu_percent_per_agent'], '.0f')} %)  router "
                      f"{fmt(row['router_cpu_percent'], '.0f')} %  wall {row['wall_s']:.0f} s"
                      f"  received {fmt(row['received_per_step'], '.1f')}/step"
                      f"  world / monitors / recorder {_others(row)} %"
                      f"  peak MiB {_mib(row)}"
                      f"  load {load:.1f} (max {fmt(row['load_max'], '.1f')})" + (
                          f"  raw zenoh RTT {fmt(row['raw_rtt_median_ms'], '.2f')} / "
                          f"{fmt(row['raw_rtt_p99_ms'], '.1f')} ms, hop median / RTT median "
                          f"{_ratio(row['hop_median_ms'], row['raw_rtt_median_ms'])}"
                          if args.raw_rtt else ""),
                      flush=True)
                if row["sustained"]:
                    break
            best = next((r for r in tried if r["sustained"]), None)
            results.append({"N": N, "transport": transport, "tree": tree, "links": links,
                            "runs": tried,
                            "sustained_steps_per_s": 1000.0 / best["step_ms"] if best else None})
    print()
    print_table(results, periods)
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
