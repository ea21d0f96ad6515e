"""Cost of the secure mode: zenoh round trip and throughput of 1 kB puts, plain vs TLS + ACL.

Starts a pong process (this script with ``--pong``) and, from this process, for each mode:

1. ping/pong round trips of a 1 kB payload (ping on ``est/2``, echoed on ``est/1``);
2. a one-way flood of 1 kB puts on ``status/2`` (``block`` congestion control); the rate
   is measured at the receiver, between its first and last message.

Both go through :class:`broker_free_net.peer.Peer`. Modes: ``plain`` (tcp, no access
control) and ``secure`` (a fresh key set from ``socmon keys``: TLS with mutual
authentication, default-deny access control on both peers; the pinger holds agent 2's
credentials, the ponger agent 1's). CPU seconds of both processes per phase are read from
``/proc``. Prints one table and the overhead of ``secure`` against ``plain``.

Usage::

    PYTHONPATH=. python scripts/bench_secure.py [--n 2000] [--warmup 200] [--flood 20000] [--repeat 3] [--json]
"""

from __future__ import annotations

import argparse
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
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from broker_free_net.ports import listen_port  # noqa: E402
from broker_free_net.config import NetConfig  # noqa: E402
from agent.protocol.topics import open_peer
from agent.protocol.topics import make_run_keys, run_identities  # noqa: E402

PAYLOAD_BYTES = 1000
END = b"END"


def _keys(run):
    p = f"socmon/{run}"
    return {"ping": f"{p}/est/2", "pong": f"{p}/est/1", "flood": f"{p}/status/2", "report": f"{p}/status/1"}


def _net(run, keys_dir, identity, listen=None, connect=None):
    proto = "tls" if keys_dir else "tcp"
    return NetConfig(run=run, listen=(listen or f"{proto}/127.0.0.1:{listen_port()}",),
                     connect=(connect,) if connect else (),
                     keys=keys_dir, identity=identity if keys_dir else None)


def run_pong(run, listen, keys_dir) -> int:
    """Echo pings; count flood messages; report count and span when END arrives."""
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    k = _keys(run)
    with open_peer(_net(run, keys_dir, "agent-1", listen=listen), "agent", 1) as peer:
        ping_in = peer.subscribe(k["ping"], maxlen=1 << 16)
        flood_in = peer.subscribe(k["flood"], maxlen=1 << 17)
        peer.publisher(k["pong"], block=True)
        peer.publisher(k["report"], block=True)
        count, first, last = 0, None, None
        expected = None  # set by "END <n>": report once n arrived or 5 s passed without any
        while not stop:
            peer.wait(timeout=0.2)
            for item in flood_in.drain():
                count += 1
                first = first if first is not None else item.arrival
                last = item.arrival
            for item in ping_in.drain():
                if item.payload.startswith(END):
                    expected = (int(item.payload.split()[1]), time.monotonic())
                else:
                    peer.put(k["pong"], item.payload)
            if expected and (count >= expected[0] or time.monotonic() - max(expected[1], last or 0) > 5):
                span = (last - first) if count > 1 else 0.0
                peer.put(k["report"], json.dumps({"count": count, "span": span}).encode())
                count, first, last, expected = 0, None, None, None
    return 0


def _cpu(pid) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def bench_mode(mode, n, warmup, flood) -> dict:
    run = f"bench{os.getpid()}{mode}"
    tmp = tempfile.TemporaryDirectory()
    keys_dir = None
    if mode == "secure":
        keys_dir = str(make_run_keys(Path(tmp.name) / "keys", run, run_identities(2)).dir)
    proto = "tls" if keys_dir else "tcp"
    listen = f"{proto}/127.0.0.1:{listen_port()}"
    cmd = [sys.executable, str(Path(__file__).resolve()), "--pong", "--run", run, "--listen", listen]
    if keys_dir:
        cmd += ["--keys", keys_dir]
    pong = subprocess.Popen(cmd, env=dict(os.environ, PYTHONPATH=str(ROOT)), start_new_session=True)
    k = _keys(run)
    payload = bytes(range(256)) * (PAYLOAD_BYTES // 256) + bytes(PAYLOAD_BYTES % 256)
    try:
        deadline = time.monotonic() + 30
        while True:  # the pong may not listen yet; a secure connect retries for 10 s only
            try:
                peer = open_peer(_net(run, keys_dir, "agent-2", connect=listen), "agent", 2)
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        with peer:
            pong_in = peer.subscribe(k["pong"], maxlen=1 << 16)
            report_in = peer.subscribe(k["report"])
            peer.publisher(k["ping"], block=True)
            peer.publisher(k["flood"], block=True)
            deadline = time.monotonic() + 30
            while pong_in.get(timeout=0.2) is None:  # routes declared both ways
                if time.monotonic() > deadline:
                    raise RuntimeError("pong never answered")
                peer.put(k["ping"], payload)
            time.sleep(0.2)
            pong_in.drain()
            cpu0, pcpu0 = time.process_time(), _cpu(pong.pid)
            times = []
            for i in range(warmup + n):
                t0 = time.perf_counter()
                peer.put(k["ping"], payload)
                item = pong_in.get(timeout=10.0)
                if item is None or item.payload != payload:
                    raise RuntimeError(f"round trip {i}: no or wrong echo")
                if i >= warmup:
                    times.append(time.perf_counter() - t0)
            rtt_cpu = (time.process_time() - cpu0, _cpu(pong.pid) - pcpu0)
            times.sort()
            cpu0, pcpu0 = time.process_time(), _cpu(pong.pid)
            t0 = time.perf_counter()
            for _ in range(flood):
                peer.put(k["flood"], payload)
            send_s = time.perf_counter() - t0
            peer.put(k["ping"], END + b" %d" % flood)
            item = report_in.get(timeout=60.0)
            if item is None:
                raise RuntimeError("no flood report")
            report = json.loads(item.payload)
            flood_cpu = (time.process_time() - cpu0, _cpu(pong.pid) - pcpu0)
        return {
            "mode": mode, "payload_bytes": PAYLOAD_BYTES, "n": n,
            "rtt_median_us": 1e6 * statistics.median(times),
            "rtt_p99_us": 1e6 * times[min(len(times) - 1, int(0.99 * len(times)))],
            "rtt_cpu_us_per_trip": {"ping": 1e6 * rtt_cpu[0] / (warmup + n), "pong": 1e6 * rtt_cpu[1] / (warmup + n)},
            "flood": flood, "flood_received": report["count"],
            "flood_sent_per_s": flood / send_s,
            "flood_received_per_s": (report["count"] - 1) / report["span"] if report["span"] > 0 else float("nan"),
            "flood_cpu_us_per_msg": {"ping": 1e6 * flood_cpu[0] / flood, "pong": 1e6 * flood_cpu[1] / flood},
        }
    finally:
        try:
            os.killpg(pong.pid, signal.SIGTERM)
            pong.wait(timeout=10)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            os.killpg(pong.pid, signal.SIGKILL)
            pong.wait()
        tmp.cleanup()


def _median_row(runs):
    out = dict(runs[0])
    for key, value in runs[0].items():
        if isinstance(value, float):
            out[key] = statistics.median(r[key] for r in runs)
        elif isinstance(value, dict):
            out[key] = {k: statistics.median(r[key][k] for r in runs) for k in value}
    out["flood_received"] = min(r["flood_received"] for r in runs)
    out["repeats"] = len(runs)
    return out


def main(n=2000, warmup=200, flood=20000, repeat=3, as_json=False) -> list[dict]:
    """Alternate plain and secure `repeat` times (the machine's load drifts); medians."""
    runs = {"plain": [], "secure": []}
    for _ in range(repeat):
        for mode in runs:
            runs[mode].append(bench_mode(mode, n, warmup, flood))
    rows = [_median_row(runs[mode]) for mode in runs]
    if as_json:
        print(json.dumps(rows, indent=2))
        return rows
    print(f"zenoh peers on loopback, {PAYLOAD_BYTES} B payloads, {n} round trips, flood of {flood}; "
          f"medians of {repeat} alternating runs")
    print(f"{'mode':<8}{'rtt median us':>15}{'rtt p99 us':>12}{'rx msg/s':>11}{'rx MB/s':>9}"
          f"{'cpu us/msg ping+pong':>22}")
    for r in rows:
        cpu = r["flood_cpu_us_per_msg"]
        print(f"{r['mode']:<8}{r['rtt_median_us']:>15.0f}{r['rtt_p99_us']:>12.0f}"
              f"{r['flood_received_per_s']:>11.0f}{r['flood_received_per_s'] * PAYLOAD_BYTES / 1e6:>9.1f}"
              f"{cpu['ping']:>11.1f}+{cpu['pong']:<10.1f}")
    plain, secure = rows
    print(f"overhead of secure: round trip {100 * (secure['rtt_median_us'] / plain['rtt_median_us'] - 1):+.1f} %, "
          f"throughput {100 * (secure['flood_received_per_s'] / plain['flood_received_per_s'] - 1):+.1f} %, "
          f"flood CPU {100 * (sum(secure['flood_cpu_us_per_msg'].values()) / sum(plain['flood_cpu_us_per_msg'].values()) - 1):+.1f} %")
    for r in rows:
        if r["flood_received"] != r["flood"]:
            print(f"warning: {r['mode']}: {r['flood_received']} of {r['flood']} flood messages received")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pong", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--run", help=argparse.SUPPRESS)
    parser.add_argument("--listen", help=argparse.SUPPRESS)
    parser.add_argument("--keys", help=argparse.SUPPRESS)
    parser.add_argument("--n", type=int, default=2000, help="round trips (default 2000)")
    parser.add_argument("--warmup", type=int, default=200, help="round trips not counted (default 200)")
    parser.add_argument("--flood", type=int, default=20000, help="one-way flood size (default 20000)")
    parser.add_argument("--repeat", type=int, default=3, help="alternating runs per mode (default 3)")
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = parser.parse_args()
    if args.pong:
        sys.exit(run_pong(args.run, args.listen, args.keys))
    main(args.n, args.warmup, args.flood, args.repeat, args.json)
