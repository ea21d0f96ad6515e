"""Benchmark of the live runtime on this machine (prints figures; asserts nothing).

In one run, for each source tree given (this one, and ``--baseline`` trees for comparison):

1. the raw zenoh round trip between two processes (a put answered from the echo's
   callback), median and p99, measured once at the start of the benchmark; then the
   *floor*: the marginal CPU and context switches per step of a bare zenoh-python
   process (socmon's zenoh configuration, no socmon code) that receives an agent's
   messages of a step and sends its estimate, with the callback handing each sample to
   the main thread (socmon's model), with the callback publishing itself, and with the
   estimates left in zenoh's own ring buffer (``--floor-steps`` steps at each period;
   ``--floor-zenoh KEY=JSON5`` changes a zenoh setting of the round trip and the floor,
   to try one of zenoh's options without socmon);
2. ``socmon up SCENARIO`` (default paper-14-live: 3 agents + 1 standby + world + monitor)
   for ``--steps`` steps at each ``--step-ms``; a step period is *sustained* when no
   estimate was dropped or late and no sensor reading missed. Per run: the agent-to-agent
   hop (publish -> decoded in the receiving agent; median of the agents' medians, worst
   p99) and its ratio to the raw round trip, the world's worst lag behind its schedule,
   and the **CPU per step** of each process: the children's CPU time (user + system, from
   ``wait4``) of the run minus that of a short run of ``--short-steps`` steps (start-up,
   imports, handshake), divided by the difference in steps;
3. a profile of one agent's main thread (cProfile with a thread-CPU clock, enabled by a
   ``sitecustomize`` module this script puts on the children's ``PYTHONPATH``, so that it
   works on any tree), over ``--profile-steps`` steps at the first step period: the
   functions with the most CPU, and how the process's CPU splits between the main thread
   and zenoh's threads.

CPU seconds per step are much less disturbed by other work on a shared machine than
wall-clock figures (hop, lag, sustained periods), which vary from run to run.

Usage::

    python scripts/bench_runtime.py [--steps 10000] [--step-ms 10,4,2] [--baseline /work/main]
"""

from __future__ import annotations

import argparse
import json
import os
import pstats
import re
import resource
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import deque
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SAMPSON_EDGES = next((p / "shared" / "data" / "sampson" / "sampson_samplike_edges.csv"
                      for p in (ROOT.parent, ROOT.parent.parent)
                      if (p / "shared" / "data" / "sampson").is_dir()), Path("/nonexistent"))
SAMPSON_TOML = """\
name = "sampson-like"
[social]
edges = "{edges}"
self_weight = true
seed = 3
spectral_radius = 0.98
process_noise = 0.1
[agents]
measure = [["1"], ["5"], ["12"], ["18"]]
measurement_noise = 0.1
standby = 1
[network]
topology = "cycle"
self_weight = 0.5
"""

#: imported by every child of a profiled run (``PYTHONPATH``); profiles ``agent`` processes
PROFILE_HOOK = '''\
import os, sys
_out = os.environ.get("SOCMON_BENCH_PROFILE")
if _out and len(sys.argv) > 1 and sys.argv[1] == "agent":
    import cProfile, functools, importlib.abc, importlib.machinery, time

    def _profiled(run_agent):
        @functools.wraps(run_agent)
        def wrapper(*args, **kwargs):
            prof = cProfile.Profile(time.thread_time)
            t0 = (time.thread_time(), time.process_time())
            prof.enable()
            try:
                return run_agent(*args, **kwargs)
            finally:
                prof.disable()
                ident = sys.argv[sys.argv.index("--id") + 1] if "--id" in sys.argv else "x"
                prof.dump_stats(os.path.join(_out, f"agent-{ident}.prof"))
                with open(os.path.join(_out, f"agent-{ident}.cpu"), "w") as f:
                    f.write(f"{time.thread_time() - t0[0]} {time.process_time() - t0[1]}\\n")
        return wrapper

    class _Wrap(importlib.abc.MetaPathFinder):
        """Wraps agent.node.process.run_agent once the module is loaded."""

        def find_spec(self, name, path, target=None):
            if name != "agent.node.process":
                return None
            spec = importlib.machinery.PathFinder.find_spec(name, path)
            exec_module = spec.loader.exec_module

            def exec_and_wrap(module):
                exec_module(module)
                module.run_agent = _profiled(module.run_agent)
            spec.loader.exec_module = exec_and_wrap
            return spec

    sys.meta_path.insert(0, _Wrap())
'''


# ---------------------------------------------------------------------------------
# raw zenoh round trip


#: environment variable carrying ``--floor-zenoh`` to the children (a JSON list of
#: [key, json5 value] pairs)
ZENOH_SETTINGS_ENV = "SOCMON_BENCH_ZENOH"


def _zconfig(listen=None, connect=None):
    """A socmon peer's zenoh configuration (``build_zenoh_config``), on loopback, with the
    ``--floor-zenoh`` settings on top."""
    from broker_free_net.config import NetConfig, build_zenoh_config

    config = build_zenoh_config(NetConfig(run="bench", listen=(listen,) if listen else (),
                                          connect=(connect,) if connect else (),
                                          multicast=False))
    for key, value in json.loads(os.environ.get(ZENOH_SETTINGS_ENV, "[]")):
        config.insert_json5(key, value)
    return config


def zenoh_setting(text: str) -> list:
    """``KEY=JSON5`` (a ``--floor-zenoh`` flag) -> ``[key, value]``, checked by zenoh.

    >>> zenoh_setting("transport/unicast/lowlatency=true")
    ['transport/unicast/lowlatency', 'true']
    """
    import zenoh

    from broker_free_net.config import zenoh_message

    key, sep, value = text.partition("=")
    if not sep or not key or not value:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        zenoh.Config().insert_json5(key, value)
    except Exception as exc:
        raise argparse.ArgumentTypeError(f"{text!r}: zenoh refused it: {zenoh_message(exc)}") from None
    return [key, value]


def echo(endpoint: str) -> None:
    """Child: answer every ``bench/ping`` with the same payload on ``bench/pong``."""
    import zenoh

    session = zenoh.open(_zconfig(listen=endpoint))
    pub = session.declare_publisher("bench/pong")
    session.declare_subscriber("bench/ping", lambda s: pub.put(s.payload.to_bytes()))
    signal.sigwait({signal.SIGTERM, signal.SIGINT})
    session.close()


def raw_rtt(pings: int) -> dict:
    import zenoh

    from broker_free_net.ports import listen_port

    endpoint = f"tcp/127.0.0.1:{listen_port()}"
    child = subprocess.Popen([sys.executable, __file__, "--echo", endpoint],
                             start_new_session=True)
    try:
        session = zenoh.open(_zconfig(connect=endpoint))
        got = threading.Event()
        session.declare_subscriber("bench/pong", lambda s: got.set())
        pub = session.declare_publisher("bench/ping")
        payload = bytes(200)  # about the size of an estimate of 14 states
        deadline = time.monotonic() + 30
        while not got.is_set():  # until routes exist both ways
            assert time.monotonic() < deadline, "echo never answered"
            pub.put(payload)
            got.wait(0.1)
        rtts = []
        for _ in range(pings):
            got.clear()
            t = time.perf_counter()
            pub.put(payload)
            if got.wait(2.0):
                rtts.append(time.perf_counter() - t)
        session.close()
    finally:
        os.killpg(child.pid, signal.SIGTERM)
        child.wait(10)
    rtts.sort()
    return {"n": len(rtts), "median_ms": 1e3 * statistics.median(rtts),
            "p99_ms": 1e3 * rtts[int(0.99 * (len(rtts) - 1))]}


# ---------------------------------------------------------------------------------
# the floor: bare zenoh-python processes with an agent's messages and no socmon code

#: what an agent of paper-14-live receives a step (the sensors message, two estimates)
#: and sends (its estimate), in bytes
FLOOR_IN, FLOOR_OUT = (163, 184, 184), 184


def floor_source(endpoint: str, steps: int, step_ms: float) -> None:
    """Child: publish an agent's inputs of a step every `step_ms` for `steps` steps."""
    import zenoh

    session = zenoh.open(_zconfig(listen=endpoint))
    pubs = [session.declare_publisher(f"bench/in/{i}") for i in range(len(FLOOR_IN))]
    payloads = [bytes(size) for size in FLOOR_IN]
    ready = session.declare_subscriber("bench/ready", zenoh.handlers.FifoChannel(4))
    ready.recv()                                  # the sink's routes exist
    start = time.monotonic()
    for k in range(steps):
        # the estimates first, then the readings: in a live step the neighbours' estimates
        # of step k - 1 arrive before the world's readings of step k
        for pub, payload in reversed(list(zip(pubs, payloads))):
            pub.put(payload)
        pause = start + (k + 1) * step_ms / 1e3 - time.monotonic()
        if pause > 0:
            time.sleep(pause)
    session.close()


def floor_sink(endpoint: str, steps: int, model: str) -> None:
    """Child: receive ``steps`` steps of inputs, publish one estimate a step, print its CPU.

    ``inbox``: the callback copies each sample into a queue and wakes the main thread,
    which publishes (socmon's model); ``callback``: the callback itself publishes;
    ``channel``: the estimates wait in zenoh's own ring buffer (``RingChannel``: the
    receive thread never takes the GIL for them) and the readings' callback wakes the main
    thread, which drains the rings and publishes."""
    import zenoh

    session = zenoh.open(_zconfig(connect=endpoint))
    out = session.declare_publisher("bench/out")
    payload = bytes(FLOOR_OUT)
    want = steps * len(FLOOR_IN)
    got, queue, lock, wake, done = [0], deque(), threading.Lock(), threading.Event(), \
        threading.Event()
    rings = []
    if model == "channel":
        rings = [session.declare_subscriber(f"bench/in/{i}", zenoh.handlers.RingChannel(64))
                 for i in range(1, len(FLOOR_IN))]

        def on_sample(sample):
            with lock:
                queue.append(sample.payload.to_bytes())
            wake.set()
    elif model == "callback":
        def on_sample(sample):
            sample.payload.to_bytes()
            with lock:
                got[0] += 1
                n = got[0]
            if n % len(FLOOR_IN) == 0:
                out.put(payload)
            if n >= want:
                done.set()
    else:
        def on_sample(sample):
            with lock:
                queue.append(sample.payload.to_bytes())
            wake.set()
    session.declare_subscriber("bench/in/0" if rings else "bench/in/*",
                               zenoh.handlers.Callback(on_sample, indirect=False))
    ready = session.declare_publisher("bench/ready")
    deadline = time.monotonic() + 60 + steps * 0.05
    while not got[0] and not queue and time.monotonic() < deadline:
        ready.put(b"")
        time.sleep(0.05)
    if model == "callback":
        done.wait(max(0.0, deadline - time.monotonic()))
    else:
        while got[0] < want and time.monotonic() < deadline:
            wake.wait(0.25)
            wake.clear()
            with lock:
                items = list(queue)
                queue.clear()
            for _ in items:
                got[0] += 1
                for ring in rings:               # channel: the estimates, without a wake-up
                    sample = ring.try_recv()
                    while sample is not None:
                        sample.payload.to_bytes()
                        got[0] += 1
                        sample = ring.try_recv()
                if rings or got[0] % len(FLOOR_IN) == 0:
                    out.put(payload)
    usage = resource.getrusage(resource.RUSAGE_SELF)
    switches = 0
    for status in Path("/proc/self/task").glob("*/status"):
        for line in status.read_text().splitlines():
            if "ctxt_switches" in line:
                switches += int(line.split()[1])
    print(json.dumps({"received": got[0], "cpu_s": usage.ru_utime + usage.ru_stime,
                      "switches": switches}), flush=True)
    os._exit(0)                                   # no session close: the source may be gone


def floor_run(steps: int, step_ms: float, model: str) -> dict:
    from broker_free_net.ports import listen_port

    endpoint = f"tcp/127.0.0.1:{listen_port()}"
    args = [str(steps), str(step_ms)]
    source = subprocess.Popen([sys.executable, __file__, "--floor-source", endpoint, *args],
                              start_new_session=True)
    try:
        sink = subprocess.run([sys.executable, __file__, "--floor-sink", endpoint, str(steps),
                               model], capture_output=True, text=True, start_new_session=True,
                              timeout=120 + steps * step_ms / 1e3 * 3)
    finally:
        try:
            os.killpg(source.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass
        source.wait(10)
    if sink.returncode != 0:
        raise RuntimeError(f"floor sink failed: {sink.stderr[-2000:]}")
    return json.loads(sink.stdout)


def floor(steps: int, short_steps: int, step_ms: float) -> dict:
    """Marginal CPU ms and context switches per step of a bare zenoh-python 'agent'."""
    out = {}
    for model in ("inbox", "callback", "channel"):
        short, long = floor_run(short_steps, step_ms, model), floor_run(steps, step_ms, model)
        extra = steps - short_steps
        out[model] = {"cpu_ms_per_step": 1e3 * (long["cpu_s"] - short["cpu_s"]) / extra,
                      "switches_per_step": (long["switches"] - short["switches"]) / extra,
                      "received": long["received"]}
    return out


# ---------------------------------------------------------------------------------
# the runtime


def run_up(tree: Path, scenario: str, gains: Path, steps: int, step_ms: float, out: Path,
           profile_dir: Path | None = None) -> dict:
    """``socmon up`` of ``tree``; its JSON summary plus the world's worst lag."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    if profile_dir is not None:
        profile_dir.mkdir(parents=True, exist_ok=True)
        (profile_dir / "sitecustomize.py").write_text(PROFILE_HOOK)
        env["PYTHONPATH"] += os.pathsep + str(profile_dir)
        env["SOCMON_BENCH_PROFILE"] = str(profile_dir)
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    proc = subprocess.run([sys.executable, "-m", "agent.cli", "up", scenario,
                           "--steps", str(steps), "--step-ms", str(step_ms), "--gains",
                           str(gains), "--out", str(out), "--json", "--quiet"],
                          cwd=tree, env=env, capture_output=True, text=True,
                          timeout=180 + steps * step_ms / 1000 * 3, start_new_session=True)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"up failed ({proc.returncode}): {proc.stderr[-2000:]}")
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    summary = json.loads(proc.stdout)
    # the `up` process itself (the recorder): every CPU second reaped below us, minus its
    # children's
    total = (after.ru_utime + after.ru_stime) - (before.ru_utime + before.ru_stime)
    summary["cpu_s"]["recorder"] = total - sum(v or 0.0 for v in summary["cpu_s"].values())
    log = (out / "logs" / "world.log").read_text()
    m = re.search(r"worst lag ([0-9.]+) ms", log)
    summary["world_lag_ms"] = float(m.group(1)) if m else float("nan")
    return summary


def cpu_ms_per_step(long: dict, short: dict) -> dict:
    """Marginal CPU ms per step of each process: (long run - short run) / extra steps."""
    extra = long["steps"] - short["steps"]
    out = {}
    for name, s in long["cpu_s"].items():
        base = short["cpu_s"].get(name)
        out[name] = (1e3 * (s - base) / extra if s is not None and base is not None
                     and extra > 0 else None)
    return out


def describe(summary: dict, steps: int, step_ms: float, rtt_ms: float) -> dict:
    hops = [h for h in summary.get("hop_ms", {}).values() if h]
    ok = (summary["drops"] == 0 and summary["late"] == 0 and summary["sensor_missed"] == 0
          and summary["steps"] == steps and "error" not in summary)
    hop = statistics.median(h["median"] for h in hops) if hops else None
    return {
        "step_ms": step_ms, "sustained": ok, "steps": summary["steps"],
        "drops": summary["drops"], "late": summary["late"],
        "sensor_missed": summary["sensor_missed"],
        "hop_median_ms": hop, "hop_p99_ms": max(h["p99"] for h in hops) if hops else None,
        "hop_over_rtt": hop / rtt_ms if hop else None,
        "cpu_s": summary["cpu_s"], "world_lag_ms": summary["world_lag_ms"],
    }


def profile_summary(profile_dir: Path, top: int) -> str:
    """The top functions (own thread CPU) of agent 1's profile, and the thread split."""
    prof = profile_dir / "agent-1.prof"
    if not prof.is_file():
        return "  (no profile written: did agent 1 exit normally?)"
    lines = []
    cpu = (profile_dir / "agent-1.cpu").read_text().split()
    main_s, proc_s = float(cpu[0]), float(cpu[1])
    lines.append(f"  agent 1 CPU in run_agent: main thread {main_s:.2f} s, zenoh's and other threads "
                 f"{proc_s - main_s:.2f} s (process {proc_s:.2f} s)")
    stats = pstats.Stats(str(prof))
    rows = sorted(stats.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    total = sum(v[2] for v in stats.stats.values()) or 1.0
    lines.append(f"  {'own s':>7} {'cum s':>7} {'calls':>8}  function (main thread, cProfile "
                 "with thread CPU time; overhead included)")
    for (file, line, func), (cc, nc, tt, ct, _) in rows:
        where = f"{Path(file).name}:{line}" if line else file
        lines.append(f"  {tt:7.2f} {ct:7.2f} {nc:8d}  {func} ({where}) {100 * tt / total:.0f}%")
    return "\n".join(lines)


def bench_tree(tree: Path, label: str, specs: dict, tmp: Path, args, rtt: dict) -> dict:
    from design.scenario import load_scenario

    results = {}
    for name in args.scenarios.split(","):
        if name not in specs:
            print(f"{name}: skipped (data not found)")
            continue
        s = load_scenario(specs[name])
        gains = tmp / f"{name}.npz"
        if not gains.exists():
            # a certified gain (a random one diverges: its estimates are then refused as
            # implausible and counted as drops, and the agents do other work)
            design = subprocess.run(
                [sys.executable, "-m", "agent.cli", "design", specs[name], "--target", "0.97",
                 "--out", str(gains)], cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                capture_output=True, text=True, timeout=600)
            if design.returncode != 0:
                raise RuntimeError(f"design {name} failed: {design.stderr[-2000:]}")
        periods = [float(x) for x in args.step_ms.split(",")]
        print(f"\n[{label}] {tree}\n{name}: n = {s.n}, {s.N} agents + {s.standby} standby "
              f"+ world + monitor, {args.steps} steps (CPU per step: minus a "
              f"{args.short_steps}-step run)", flush=True)
        short = run_up(tree, specs[name], gains, args.short_steps, periods[0],
                       tmp / f"{label}-{name}-short")
        agents = [f"agent-{a}" for a in range(1, s.N + 1)]
        standby = [f"agent-{a}" for a in range(s.N + 1, s.N + s.standby + 1)]
        print(f"{'step_ms':>8} {'ok':>4} {'drops':>6} {'late':>5} {'missed':>6} {'hop med':>8} "
              f"{'/rtt':>5} {'hop p99':>8} {'lag ms':>7}  CPU ms/step: agent (mean) standby "
              "world monitor recorder")
        rows = []
        for step_ms in periods:
            summary = run_up(tree, specs[name], gains, args.steps, step_ms,
                             tmp / f"{label}-{name}-{step_ms}")
            row = describe(summary, args.steps, step_ms, rtt["median_ms"])
            per = cpu_ms_per_step(summary, short)
            row["cpu_ms_per_step"] = per

            def mean(names):
                vals = [per.get(n) for n in names if per.get(n) is not None]
                return statistics.mean(vals) if vals else float("nan")

            row["agent_cpu_ms_per_step"] = mean(agents)
            rows.append(row)
            print(f"{step_ms:8g} {'yes' if row['sustained'] else 'no':>4} {row['drops']:6d} "
                  f"{row['late']:5d} {row['sensor_missed']:6d} "
                  f"{row['hop_median_ms'] or float('nan'):8.3f} "
                  f"{row['hop_over_rtt'] or float('nan'):5.1f} "
                  f"{row['hop_p99_ms'] or float('nan'):8.3f} {row['world_lag_ms']:7.1f}  "
                  f"{mean(agents):.3f} {mean(standby):.3f} {mean(['world']):.3f} "
                  f"{mean(['monitor']):.3f} {mean(['recorder']):.3f}", flush=True)
            if not row["sustained"] and not args.keep_going:
                print(f"{'':8} (shorter periods not tried)")
                break
        best = [r["step_ms"] for r in rows if r["sustained"]]
        print(f"{name}: smallest sustained step_ms = {min(best) if best else 'none tried'}")
        prof_dir = tmp / f"{label}-{name}-profile"
        if args.profile_steps:
            run_up(tree, specs[name], gains, args.profile_steps, periods[0],
                   tmp / f"{label}-{name}-profiled", profile_dir=prof_dir)
            print(f"profile of agent 1, {args.profile_steps} steps of {periods[0]:g} ms:")
            print(profile_summary(prof_dir, args.profile_top), flush=True)
        results[name] = {"short_run_cpu_s": short["cpu_s"], "short_steps": short["steps"],
                         "rows": rows}
    return results


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument("--short-steps", type=int, default=300,
                        help="steps of the run whose CPU is subtracted (start-up)")
    parser.add_argument("--step-ms", default="10,4,2")
    parser.add_argument("--pings", type=int, default=2000)
    parser.add_argument("--scenarios", default="paper-14-live",
                        help="comma-separated: paper-14-live, paper-14, sampson-like")
    parser.add_argument("--tree", default=str(ROOT), help="source tree to run (default: this)")
    parser.add_argument("--baseline", action="append", default=[], metavar="TREE",
                        help="another source tree measured the same way, e.g. /work/main")
    parser.add_argument("--profile-steps", type=int, default=2000,
                        help="steps of the profiled run (0: no profile)")
    parser.add_argument("--profile-top", type=int, default=15)
    parser.add_argument("--keep-going", action="store_true",
                        help="try every period even after one is not sustained")
    parser.add_argument("--floor-steps", type=int, default=2000,
                        help="steps of the bare zenoh-python floor at each period (0: none)")
    parser.add_argument("--floor-zenoh", type=zenoh_setting, action="append", default=[],
                        metavar="KEY=JSON5",
                        help="a zenoh setting for the raw round trip and the floor only "
                             "(repeatable), e.g. transport/unicast/lowlatency=true")
    parser.add_argument("--floor-only", action="store_true",
                        help="measure the raw round trip and the floor, run no socmon tree")
    parser.add_argument("--echo", help=argparse.SUPPRESS)
    parser.add_argument("--floor-source", nargs=3, help=argparse.SUPPRESS)
    parser.add_argument("--floor-sink", nargs=3, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo(args.echo)
        return 0
    if args.floor_source:
        endpoint, steps, step_ms = args.floor_source
        floor_source(endpoint, int(steps), float(step_ms))
        return 0
    if args.floor_sink:
        endpoint, steps, model = args.floor_sink
        floor_sink(endpoint, int(steps), model)
        return 0
    trees = [(Path(args.tree).resolve(), "this")] + [
        (Path(b).resolve(), f"baseline{i + 1}" if len(args.baseline) > 1 else "baseline")
        for i, b in enumerate(args.baseline)]
    for tree, _ in trees:
        if not ((tree / "agent" / "cli" / "main.py").is_file()
                or (tree / "agent" / "cli.py").is_file()):
            print(f"bench_runtime: {tree}: not a socmon source tree (no agent/cli/main.py)",
                  file=sys.stderr)
            return 2

    if args.floor_zenoh:
        os.environ[ZENOH_SETTINGS_ENV] = json.dumps(args.floor_zenoh)
        print("zenoh settings of the raw round trip and the floor: "
              + ", ".join(f"{k}={v}" for k, v in args.floor_zenoh))
    print(f"machine: {os.cpu_count()} cores, load average "
          f"{' '.join(f'{x:.2f}' for x in os.getloadavg())} (shared: wall-clock figures vary; "
          "CPU ms per step much less)")
    rtt = raw_rtt(args.pings)
    print(f"raw zenoh round trip (2 processes, loopback, {rtt['n']} pings): "
          f"median {rtt['median_ms']:.3f} ms, p99 {rtt['p99_ms']:.3f} ms")
    results = {"raw_rtt": rtt, "trees": {}, "floor": {}}
    if args.floor_steps:
        print(f"floor: a bare zenoh-python process receiving an agent's {len(FLOOR_IN)} "
              f"messages a step and sending its one ({args.floor_steps} steps minus "
              f"{args.short_steps // 2}; no socmon code)")
        for step_ms in [float(x) for x in args.step_ms.split(",")]:
            fl = floor(args.floor_steps, args.short_steps // 2, step_ms)
            results["floor"][str(step_ms)] = fl
            print(f"  {step_ms:g} ms steps: " + "; ".join(
                f"{model} model {f['cpu_ms_per_step']:.3f} CPU ms/step, "
                f"{f['switches_per_step']:.1f} context switches/step"
                for model, f in fl.items()), flush=True)
    tmp = Path(tempfile.mkdtemp(prefix="bench_runtime_"))
    if args.floor_only:
        trees = []
    specs = {"paper-14": "paper-14", "paper-14-live": "paper-14-live"}
    if SAMPSON_EDGES.is_file():
        (tmp / "sampson-like.toml").write_text(SAMPSON_TOML.format(edges=SAMPSON_EDGES))
        specs["sampson-like"] = str(tmp / "sampson-like.toml")
    for tree, label in trees:
        results["trees"][label] = {"path": str(tree),
                                   "runs": bench_tree(tree, label, specs, tmp, args, rtt)}
    (tmp / "bench_runtime.json").write_text(json.dumps(results, indent=2))
    print(f"\nfigures: {tmp / 'bench_runtime.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
