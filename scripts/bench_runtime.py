"""Benchmark of the live runtime on this machine (prints figures; asserts nothing).

1. Raw zenoh round trip between two processes (a put answered from the echo's callback):
   median and p99.
2. For paper-14 and a Sampson-like scenario (18 nodes, 4 agents + 1 standby + world):
   ``socmon up`` for ``--steps`` steps at decreasing ``step_ms``; a step period is
   *sustained* when no estimate was dropped or late and no sensor reading missed. For each
   run: the agent-to-agent hop (publish -> decoded in the receiving agent, median / p99
   over all agents), CPU per process (% of one core over the run) and the world's worst
   lag behind its schedule.

Usage::

    python scripts/bench_runtime.py [--steps 2000] [--step-ms 10,5,3,2,1] [--pings 2000]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

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


# ---------------------------------------------------------------------------------
# raw zenoh round trip


def _zconfig(listen=None, connect=None):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    conf.insert_json5("connect/endpoints", json.dumps([connect] if connect else []))
    return conf


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
# the runtime


def run_up(scenario: str, gains: Path, steps: int, step_ms: float, out: Path) -> dict:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.run([sys.executable, "-m", "agent.cli", "up", scenario,
                           "--steps", str(steps), "--step-ms", str(step_ms), "--gains",
                           str(gains), "--out", str(out), "--json", "--quiet"],
                          cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=120 + steps * step_ms / 1000 * 3, start_new_session=True)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"up failed ({proc.returncode}): {proc.stderr[-2000:]}")
    summary = json.loads(proc.stdout)
    log = (out / "logs" / "world.log").read_text()
    m = re.search(r"worst lag ([0-9.]+) ms", log)
    summary["world_lag_ms"] = float(m.group(1)) if m else float("nan")
    return summary


def describe(summary: dict, steps: int, step_ms: float) -> dict:
    span = steps * step_ms / 1000.0
    hops = [h for h in summary.get("hop_ms", {}).values() if h]
    cpu = {k: (100.0 * v / span if v is not None else None)
           for k, v in summary["cpu_s"].items()}
    ok = (summary["drops"] == 0 and summary["late"] == 0 and summary["sensor_missed"] == 0
          and summary["steps"] == steps and "error" not in summary)
    return {
        "step_ms": step_ms, "sustained": ok, "drops": summary["drops"],
        "late": summary["late"], "sensor_missed": summary["sensor_missed"],
        "hop_median_ms": statistics.median(h["median"] for h in hops) if hops else None,
        "hop_p99_ms": max(h["p99"] for h in hops) if hops else None,
        "cpu_percent": cpu, "world_lag_ms": summary["world_lag_ms"],
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--step-ms", default="10,5,3,2,1")
    parser.add_argument("--pings", type=int, default=2000)
    parser.add_argument("--scenarios", default="paper-14,sampson-like")
    parser.add_argument("--echo", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.echo:
        echo(args.echo)
        return 0
    from design.gains import save_gains
    from design.scenario import load_scenario

    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()}")
    rtt = raw_rtt(args.pings)
    print(f"raw zenoh round trip (2 processes, loopback, {rtt['n']} pings): "
          f"median {rtt['median_ms']:.3f} ms, p99 {rtt['p99_ms']:.3f} ms")
    tmp = Path(tempfile.mkdtemp(prefix="bench_runtime_"))
    specs = {"paper-14": "paper-14"}
    if SAMPSON_EDGES.is_file():
        (tmp / "sampson-like.toml").write_text(SAMPSON_TOML.format(edges=SAMPSON_EDGES))
        specs["sampson-like"] = str(tmp / "sampson-like.toml")
    results = {"raw_rtt": rtt, "runs": {}}
    for name in args.scenarios.split(","):
        if name not in specs:
            print(f"{name}: skipped (data not found)")
            continue
        s = load_scenario(specs[name])
        rng = np.random.default_rng(0)
        gains = tmp / f"{name}.npz"
        save_gains(gains, [0.3 * rng.normal(size=(s.n, len(m))) for m in s.measure],
                   {"method": "benchmark (timing only)"})
        print(f"\n{name}: n = {s.n}, {s.N} agents + {s.standby} standby + world, "
              f"{args.steps} steps")
        print(f"{'step_ms':>8} {'ok':>4} {'drops':>6} {'late':>5} {'hop med':>8} "
              f"{'hop p99':>8} {'lag':>7}  cpu % (world, agents...)")
        rows = []
        for step_ms in [float(x) for x in args.step_ms.split(",")]:
            summary = run_up(specs[name], gains, args.steps, step_ms, tmp / f"{name}-{step_ms}")
            row = describe(summary, args.steps, step_ms)
            rows.append(row)
            cpu = " ".join(f"{v:.0f}" if v is not None else "?"
                           for v in row["cpu_percent"].values())
            print(f"{step_ms:8g} {'yes' if row['sustained'] else 'no':>4} {row['drops']:6d} "
                  f"{row['late']:5d} {row['hop_median_ms'] or float('nan'):8.3f} "
                  f"{row['hop_p99_ms'] or float('nan'):8.3f} {row['world_lag_ms']:7.1f}  {cpu}",
                  flush=True)
            if not row["sustained"]:
                break
        best = [r["step_ms"] for r in rows if r["sustained"]]
        print(f"{name}: smallest sustained step_ms = {min(best) if best else 'none tried'}")
        results["runs"][name] = rows
    (tmp / "bench_runtime.json").write_text(json.dumps(results, indent=2))
    print(f"\nfigures: {tmp / 'bench_runtime.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
