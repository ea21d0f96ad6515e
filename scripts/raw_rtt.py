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
         start_timeout: float = 30.0, timeout: float = 5.0) -> int:
    """Ping once a period until SIGTERM or ``count``; write ``out`` (JSON: the summary and
    every round trip as ``[wall-clock time sent, seconds]``) whatever ends it, a ping
    without its pong within ``timeout`` counted ``lost``."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    got = {}
    arrived = threading.Condition()

    def on_pong(sample):
        with arrived:
            got[struct.unpack("<q", sample.payload.to_bytes())[0]] = time.perf_counter()
            arrived.notify_all()

    samples, lost, answered = [], 0, False
    try:
        with _session(connect=connect) as s:
            pub = s.declare_publisher(PING)
            s.declare_subscriber(PONG, on_pong)
            deadline = time.monotonic() + start_timeout        # the pong's first answer
            while not stop.is_set() and time.monotonic() < deadline:
                pub.put(struct.pack("<q", -1))
                with arrived:
                    if arrived.wait_for(lambda: -1 in got, timeout=0.1):
                        answered = True
                        break
            if not answered:
                print("raw_rtt: no pong answered" if not stop.is_set() else
                      "raw_rtt: stopped before the pong answered", file=sys.stderr)
            period, seq = period_ms / 1000.0, 0
            next_at = time.perf_counter()
            while answered and not stop.is_set() and (count is None or seq < count):
                wall, t0 = time.time(), time.perf_counter()
                pub.put(struct.pack("<q", seq))
                with arrived:
                    if arrived.wait_for(lambda: seq in got or stop.is_set(), timeout=timeout) \
                            and seq in got:
                        samples.append([wall, got.pop(seq) - t0])
                    elif not stop.is_set():
                        lost += 1
                    got.clear()                    # a pong later than its deadline: gone
                seq += 1
                next_at = max(next_at + period, time.perf_counter())   # no burst after a stall
                stop.wait(max(0.0, next_at - time.perf_counter()))
    finally:
        rtts = sorted(r for _, r in samples)
        summary = {"n": len(rtts), "lost": lost, "period_ms": period_ms,
                   "median_ms": 1e3 * statistics.median(rtts) if rtts else None,
                   "p99_ms": 1e3 * rtts[int(0.99 * (len(rtts) - 1))] if rtts else None,
                   "samples": samples}
        with open(out, "w") as f:
            json.dump(summary, f)
    return 0 if answered else 1


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
    import zenoh

    try:
        if args.role == "pong":
            return pong(args.listen)
        return ping(args.connect, args.period_ms, args.out, args.count)
    except zenoh.ZError as exc:          # a bad endpoint, a port taken: named, exit 2
        print(f"raw_rtt: {args.role}: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
