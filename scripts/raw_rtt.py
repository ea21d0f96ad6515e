"""The raw zenoh round trip on this host: the floor a socmon hop is compared with.

Two bare zenoh-python peers on loopback, nothing of socmon between them: ``pong`` answers
every ping from inside zenoh's callback; ``ping`` sends one ping a period (as an agent
publishes one estimate a step, so that both pay the same wake-ups) and keeps each round
trip, until SIGTERM or ``--count``, then writes them as JSON. ``scripts/bench_scale.py
--raw-rtt`` runs the pair beside each run: the hop and the floor measured under the same
load.

Usage::

    python scripts/raw_rtt.py pong --listen tcp/127.0.0.1:7601
    python scripts/raw_rtt.py ping --connect tcp/127.0.0.1:7601 --period-ms 10 --out rtt.json
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import struct
import sys
import threading
import time

PING, PONG = "socmon-bench/raw/ping", "socmon-bench/raw/pong"


def _session(listen=None, connect=None):
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("transport/shared_memory/enabled", "false")   # as socmon's peers
    conf.insert_json5("listen/endpoints", json.dumps([listen] if listen else []))
    conf.insert_json5("connect/endpoints", json.dumps([connect] if connect else []))
    return zenoh.open(conf)


def pong(listen: str) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with _session(listen=listen) as s:
        pub = s.declare_publisher(PONG)
        sub = s.declare_subscriber(PING, lambda sample: pub.put(sample.payload.to_bytes()))
        while not stop.wait(0.5):
            pass
        sub.undeclare()
    return 0


def ping(connect: str, period_ms: float, out: str, count: int | None = None,
         start_timeout: float = 30.0) -> int:
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    got = {}
    answered = threading.Event()

    def on_pong(sample):
        got[struct.unpack("<q", sample.payload.to_bytes())[0]] = time.perf_counter()
        answered.set()

    rtts, lost = [], 0
    with _session(connect=connect) as s:
        pub = s.declare_publisher(PING)
        s.declare_subscriber(PONG, on_pong)
        deadline = time.monotonic() + start_timeout        # the pong's first answer
        while not got and time.monotonic() < deadline and not stop.is_set():
            pub.put(struct.pack("<q", -1))
            answered.wait(0.1)
        if not got:
            print("raw_rtt: no pong answered", file=sys.stderr)
            return 1
        period = period_ms / 1000.0
        seq, next_at = 0, time.perf_counter()
        while not stop.is_set() and (count is None or seq < count):
            answered.clear()
            t0 = time.perf_counter()
            pub.put(struct.pack("<q", seq))
            if answered.wait(1.0) and seq in got:
                rtts.append(got.pop(seq) - t0)
            else:
                lost += 1
            seq += 1
            next_at += period
            stop.wait(max(0.0, next_at - time.perf_counter()))
    summary = {"n": len(rtts), "lost": lost, "period_ms": period_ms,
               "median_ms": 1e3 * statistics.median(rtts) if rtts else None,
               "p99_ms": (1e3 * sorted(rtts)[int(0.99 * (len(rtts) - 1))] if rtts else None)}
    with open(out, "w") as f:
        json.dump(summary, f)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="role", required=True)
    p = sub.add_parser("pong")
    p.add_argument("--listen", required=True)
    p = sub.add_parser("ping")
    p.add_argument("--connect", required=True)
    p.add_argument("--period-ms", type=float, default=10.0)
    p.add_argument("--out", required=True)
    p.add_argument("--count", type=int, default=None)
    args = ap.parse_args(argv)
    if args.role == "pong":
        return pong(args.listen)
    return ping(args.connect, args.period_ms, args.out, args.count)


if __name__ == "__main__":
    sys.exit(main())
