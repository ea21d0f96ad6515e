"""RSS of a live agent before and after floods of malformed messages (prints a table).

A paper-14-live run (world + 4 agents, loopback) is started; this script joins the mesh and
sends agent 1, one class after the other, ``--count`` hostile messages of each class on a
key it subscribes to. After each class it waits until agent 1 has accounted for them
(counted malformed, lost to a full inbox, or a rejected assignment: whichever applies) and
reads the agent's resident set size (VmRSS) from /proc. The whole flood is sent ``--passes``
times. The target is an RSS after the whole flood within 5 MB of the RSS before it, and an
agent still stepping; a one-time rise in the first pass that does not come back in later
passes is the allocator's high-water mark, not a leak.

With ``--live``, a whole ``socmon up`` run (world, 3 agents, a standby, two monitors and
``up``'s own recorder; plain mode) is attacked instead, as an outsider joined as a zenoh
client:

1. *evidence*: for ``--attack-steps`` steps, every step, statuses that speak for another
   agent or carry an epoch of 2^62, rosters unsigned or signed with a key not the run's,
   estimates of 1e300 published as agent 1 and readings of 1e300;
2. *flood*: ``--count`` malformed messages of each class on the keys the monitor and the
   recorder read (statuses, rosters, estimates, the truth, the monitor's events);
3. agent 1 is killed once the attacks are over (``--kill``), and the run ends.

It prints the RSS of every process before and after each phase, then what the run made of
it (read from ``summary.json``): the agents convicted, the evidence the monitor refused (by
reason), the values refused as implausible, the highest epoch of any roster in force,
whether the crash after it was recovered, and the steady MSE against its prediction.

With ``--slow-subscriber``, ``socmon up paper-14-live`` runs once alone and once per
placement with an outsider subscribed to every key of the run that sleeps
``--sleep-s`` in its callback (zenoh's receive thread held, TCP back-pressure on whoever
sends to it): connected as a peer to agent 1, to the world and to ``up``'s recorder, and as
a client to agent 1 and to the recorder. It prints, per run, the messages the outsider
took, the drops and late estimates, the convictions and the steady MSE (which, with the
run's seed fixed, equals the run alone's when nobody was held back).

Usage::

    python scripts/bench_hostile.py [--count 10000] [--step-ms 20] [--passes 2]
    python scripts/bench_hostile.py --live [--count 10000] [--attack-steps 500]
    python scripts/bench_hostile.py --slow-subscriber [--steps 1500] [--sleep-s 0.5]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from agent.protocol import wire  # noqa: E402
from agent.protocol import topics  # noqa: E402
from broker_free_net.codec import MAX_PAYLOAD_BYTES  # noqa: E402
from design.gains import save_gains  # noqa: E402
from design.scenario import load_scenario  # noqa: E402
from tests.runtime_procs import Deployment  # noqa: E402


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmRSS")


def classes(run: str, n: int, rng):
    """(name, key, make_payload) of every hostile class."""
    est, ctl, sensor = topics.est_key(run, 2), topics.ctl_key(run, 1), topics.sensors_key(run)
    good_est = wire.encode_est(2, 3, np.zeros(n), 0, 0.0)
    junk = rng.bytes(250_000)
    deep = b"\x82\xa1v\x01\xa1x" + b"\x91" * 5000 + b"\xc0"
    many = b"\x82\xa1v\x01\xa1x\xdd\x00\x01\x00\x00" + b"\x90" * 65536
    bad_ctl = wire.encode_ctl(1, 1, 10, [f"no-such-node-{i:0>60}" for i in range(400)],
                              {2: 0.5}, 0.5, np.zeros((n, 400)))
    return [
        ("random bytes (0-50 B)", est, lambda: rng.bytes(int(rng.integers(0, 50)))),
        ("bad version", est, lambda: good_est.replace(b"\xa1v\x01", b"\xa1v\x07")),
        ("NaN estimate", est, lambda: wire.encode_est(2, 3, np.full(n, np.nan), 0, 0.0)),
        ("unknown sender", est, lambda: wire.encode_est(77, 3, np.zeros(n), 0, 0.0)),
        ("nested 5000 deep", est, lambda: deep),
        ("65 536 empty lists", est, lambda: many),
        ("250 kB junk on sensor", sensor, lambda: junk),
        ("sensor stamped 2^38", sensor, lambda: wire.encode_sensors(wire.MAX_STEP, np.ones(n))),
        ("sensor stray stamps", sensor,
         lambda: wire.encode_sensors(int(rng.integers(10**3, 10**5)), np.full(n, 1e9))),
        ("rejected assignment (400 labels)", ctl, lambda: bad_ctl),
        ("over 1 MiB on ctl", ctl, lambda: b"\x00" * (MAX_PAYLOAD_BYTES + 1024)),
    ]


def accounted(status: dict) -> int:
    return status["malformed"] + status["overflows"] + status["ctl"]["rejected"]


def main(count: int, step_ms: int, passes: int) -> int:
    s = load_scenario("paper-14-live")
    with tempfile.TemporaryDirectory() as tmp:
        gains = Path(tmp) / "g.npz"
        save_gains(gains, [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure], {"method": "bench"})
        dep = Deployment(Path(tmp), "paper-14-live", gains, n=s.n, step_ms=step_ms)
        try:
            dep.wait_for(lambda: all(dep.step_of(a) >= 20 for a in (1, 2, 3, 4)), "20 steps")
            pid = dep.children.children["agent-1"].proc.pid
            rng = np.random.default_rng(0)
            rows = []
            start_rss = rss_mb(pid)
            print(f"agent 1 (pid {pid}) at step {dep.step_of(1)}: RSS {start_rss:.1f} MB; "
                  f"{count} messages per class, step {step_ms} ms")
            for pass_, (name, key, make) in [(p, c) for p in range(1, passes + 1)
                                             for c in classes(dep.run, s.n, rng)]:
                dep.peer.publisher(key, block=True)
                dep.read()
                base, before, step0 = accounted(dep.status[1]), rss_mb(pid), dep.step_of(1)
                t0 = time.monotonic()
                size = 0
                for _ in range(count):
                    payload = make()
                    size = len(payload)
                    dep.peer.put(key, payload)
                # stray stamps are held aside (not counted) and zenoh itself drops some
                # over-size messages: wait until all are counted or the count settles
                seen = {"n": -1, "at": time.monotonic()}

                def settled(base=base, step0=step0, seen=seen):
                    n = accounted(dep.status[1]) - base
                    if n != seen["n"]:
                        seen.update(n=n, at=time.monotonic())
                    moving = dep.step_of(1) >= step0 + 5
                    return moving and (n >= count or time.monotonic() - seen["at"] > 3.0)

                try:
                    dep.wait_for(settled, name, timeout=300)
                    done = True
                except AssertionError:
                    done = False
                rows.append((f"{name} (pass {pass_})", size, accounted(dep.status[1]) - base, before, rss_mb(pid),
                             dep.step_of(1) - step0, time.monotonic() - t0, done))
            end_rss = rss_mb(pid)
            st = dep.status[1]
        finally:
            dep.close()
    print()
    print("| class | bytes | counted | RSS before (MB) | RSS after (MB) | delta (MB) "
          "| steps meanwhile | s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, size, counted, before, after, steps, secs, done in rows:
        flag = "" if done else " (timed out)"
        print(f"| {name}{flag} | {size} | {counted} | {before:.1f} | {after:.1f} | "
              f"{after - before:+.1f} | {steps} | {secs:.1f} |")
    print()
    print(f"whole flood: RSS {start_rss:.1f} -> {end_rss:.1f} MB ({end_rss - start_rss:+.1f} MB; "
          f"target within 5 MB); malformed by reason {st['malformed_reasons']}; "
          f"overflows {st['overflows']}; ctl {st['ctl']['rejected']} rejected, last error "
          f"{len(st['ctl']['last_error'])} characters")
    return 0


def _live_classes(run: str, n: int, rng):
    """(name, key, make_payload, share of --count) of the malformed flood on what the
    monitor and the recorder read."""
    deep = b"\x82\xa1v\x01\xa1x" + b"\x91" * 5000 + b"\xc0"
    return [
        ("random bytes on status/2", topics.status_key(run, 2),
         lambda: rng.bytes(int(rng.integers(0, 50))), 1.0),
        ("nested 5000 deep on status/3", topics.status_key(run, 3), lambda: deep, 1.0),
        ("250 kB junk on the roster key", topics.ctl_key(run, 0), lambda: rng.bytes(250_000),
         0.02),
        ("random bytes on est/1", topics.est_key(run, 1),
         lambda: rng.bytes(int(rng.integers(0, 50))), 1.0),
        ("NaN truth", topics.truth_key(run),
         lambda: wire.encode_truth(int(rng.integers(0, 10**5)), np.full(n, np.nan)), 1.0),
        ("random bytes on monitor events", topics.monitor_events_key(run),
         lambda: rng.bytes(int(rng.integers(0, 200))), 1.0),
    ]


def _rss_all(pids: dict) -> dict:
    out = {}
    for name, pid in pids.items():
        try:
            out[name] = rss_mb(pid)
        except (OSError, RuntimeError):
            out[name] = float("nan")          # exited (agent 1 after its kill)
    return out


def _start_up(out: Path, steps: int, step_ms: int, *flags):
    """``socmon up paper-14-live`` in its own process group; ``(process, run.json)`` once
    the run folder names the run."""
    import json
    import os
    import subprocess

    up = subprocess.Popen(
        [sys.executable, "-m", "agent.cli", "up", "paper-14-live", "--out", str(out), "--json",
         "--quiet", "--steps", str(steps), "--step-ms", str(step_ms), *flags], cwd=ROOT,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        env=dict(os.environ, PYTHONPATH=str(ROOT)))
    deadline = time.monotonic() + 120
    while not (out / "run.json").is_file():
        if up.poll() is not None or time.monotonic() > deadline:
            if up.poll() is None:
                os.killpg(up.pid, 9)
            raise SystemExit(f"up did not start: {up.stderr.read()}")
        time.sleep(0.05)
    return up, json.loads((out / "run.json").read_text())


def live(count: int, step_ms: int, attack_steps: int) -> int:
    """The ``--live`` benchmark (see the module docstring)."""
    import json
    import os
    import signal

    from agent.protocol.control_auth import ControlSigner
    from broker_free_net.codec import MessageStats
    from broker_free_net.config import NetConfig
    from tests.test_evidence_multiprocess import _status, _step_of

    s = load_scenario("paper-14-live")
    start = 100
    steps = start + attack_steps + int(120_000 / step_ms)   # room for the flood and after
    with tempfile.TemporaryDirectory() as tmp:
        gains, out = Path(tmp) / "g.npz", Path(tmp) / "run"
        save_gains(gains, [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure], {"method": "bench"})
        up, run = _start_up(out, steps, step_ms, "--gains", str(gains))
        try:
            pids = {name: p["pid"] for name, p in run["processes"].items() if p.get("pid")}
            pids["recorder (up)"] = up.pid
            rid = run["run"]
            net = NetConfig(run=rid, mode="client", connect=(run["connect"],))
            rss = {}
            with topics.open_peer(net, "attacker", 0) as peer:
                truth_in = peer.subscribe(topics.truth_key(rid), maxlen=64)
                evidence = (topics.ctl_key(rid, 0), topics.status_key(rid, 1),
                            topics.status_key(rid, 2), topics.est_key(rid, 1),
                            topics.sensors_key(rid))
                for key in evidence:
                    peer.publisher(key, block=True)
                outsider = ControlSigner.generate()
                stats, step, sent = MessageStats(), -1, 0
                while step < start:
                    step, _ = _step_of(truth_in, stats, step)
                rss["start"] = _rss_all(pids)
                print(f"run {rid}: attacking from step {step}; {len(pids)} processes")
                t0 = time.monotonic()
                while step < start + attack_steps:
                    if up.poll() is not None:
                        raise SystemExit(f"up ended during the attack: {up.stderr.read()}")
                    step, heard = _step_of(truth_in, stats, step)
                    if not heard:
                        continue
                    peer.put(topics.status_key(rid, 2), wire.encode_status(
                        _status(1, step + 5, 2 ** 62)))
                    peer.put(topics.status_key(rid, 1), wire.encode_status(
                        _status(1, step, 2 ** 61)))
                    peer.put(topics.ctl_key(rid, 0), wire.encode_roster(2 ** 62, 10 ** 6, [1, 2, 3]))
                    peer.put(topics.ctl_key(rid, 0), wire.encode_roster(
                        7, 10 ** 6, [2, 3, 4], signer=outsider, run=rid))
                    peer.put(topics.est_key(rid, 1), wire.encode_est(
                        1, step + 1, np.full(s.n, 1e300), 0, time.time()))
                    peer.put(topics.sensors_key(rid), wire.encode_sensors(
                        step + 1, np.full(s.n, 1e300)))
                    sent += 6
                print(f"evidence: {sent} forged messages over {time.monotonic() - t0:.1f} s "
                      f"(to step {step})")
                rss["evidence"] = _rss_all(pids)
                rng = np.random.default_rng(0)
                flood = 0
                for name, key, make, share in _live_classes(rid, s.n, rng):
                    peer.publisher(key, block=True)
                    t1, sent_class = time.monotonic(), max(1, int(count * share))
                    for _ in range(sent_class):
                        peer.put(key, make())
                    flood += sent_class
                    print(f"flood: {sent_class} x {name} ({time.monotonic() - t1:.1f} s)")
                step, _ = _step_of(truth_in, stats, step)
                t_wait = time.monotonic() + 5.0
                while time.monotonic() < t_wait:     # let the inboxes drain
                    step, _ = _step_of(truth_in, stats, step)
                rss["flood"] = _rss_all(pids)
                print(f"flood: {flood} messages; run at step {step}")
                if step > steps - 700:
                    raise SystemExit("the flood took too long: no room left for the crash")
                os.kill(pids["agent-1"], signal.SIGKILL)
                kill = step
                print(f"agent 1 killed at step {kill}")
            stdout, stderr = up.communicate(timeout=steps * step_ms / 1000 + 180)
        finally:
            if up.poll() is None:
                os.killpg(up.pid, signal.SIGKILL)
                up.communicate()
        rss["end"] = {}
        summary = json.loads(stdout) if stdout.strip() else {}
    print()
    print("| process | RSS at start (MB) | after the evidence attacks | after the flood | "
          "delta (MB) |")
    print("| --- | ---: | ---: | ---: | ---: |")
    for name in pids:
        a, b, c = rss["start"][name], rss["evidence"][name], rss["flood"][name]
        print(f"| {name} | {a:.1f} | {b:.1f} | {c:.1f} | {c - a:+.1f} |")
    print()
    if not summary:
        print(f"up printed no summary (exit {up.returncode}): {stderr[-2000:]}")
        return 1
    refused = sorted({(e.get("reason"), e.get("agent"))
                      for e in summary.get("evidence_refused", [])}, key=str)
    convicted = [(f["agent"], f.get("cause"), f.get("detected_step"))
                 for f in summary.get("failures", [])]
    epochs = [r["epoch"] for r in summary.get("rosters", [])]
    print(f"up exit {up.returncode}; convicted {convicted} (agent 1 killed at step {kill}); "
          f"recovered {summary.get('recovered')}")
    print(f"evidence the monitor refused (reason, agent named): {refused}")
    print(f"implausible values refused by the agents: {summary.get('implausible')}; "
          f"messages the recorder refused: {summary.get('recorder_malformed')}")
    print(f"highest roster epoch in force: {max(epochs) if epochs else None}; rosters "
          f"{len(epochs)}")
    after, exact = (summary.get("mse_steady_after_recovery"),
                    summary.get("mse_steady_exact_after_recovery"))
    print(f"mse_steady after recovery {after if after is None else f'{after:.4g}'} "
          f"(exact {exact if exact is None else f'{exact:.4g}'})")
    return 0


def slow_subscriber(steps: int, step_ms: int, sleep_s: float) -> int:
    """The ``--slow-subscriber`` benchmark (see the module docstring)."""
    import json
    import os

    import zenoh

    def run_once(target, mode, out):
        up, run = _start_up(out, steps, step_ms)
        session, taken = None, [0]
        try:
            deadline = time.monotonic() + 120
            if target is not None:
                cfg = zenoh.Config()
                cfg.insert_json5("mode", json.dumps(mode))
                cfg.insert_json5("connect/endpoints",
                                 json.dumps([run["processes"][target]["endpoint"]]))
                cfg.insert_json5("scouting/multicast/enabled", "false")
                while session is None:       # the target may not listen yet
                    try:
                        session = zenoh.open(cfg)
                    except zenoh.ZError:
                        if time.monotonic() > deadline:
                            raise
                        time.sleep(0.2)

                def slow(_sample):
                    taken[0] += 1
                    time.sleep(sleep_s)
                session.declare_subscriber(f"socmon/{run['run']}/**", slow)
            up.communicate(timeout=steps * step_ms / 1000 + 300)
        finally:
            if up.poll() is None:
                os.killpg(up.pid, 9)
        # the outsider's session is left open: closing it would wait for every sample
        # queued behind its sleeping callback
        return json.loads((out / "summary.json").read_text()), taken[0]

    placements = [(None, None), ("agent-1", "peer"), ("world", "peer"),
                  ("recorder", "peer"), ("agent-1", "client"), ("recorder", "client")]
    print(f"paper-14-live, {steps} steps at {step_ms} ms, an outsider sleeping {sleep_s:g} s "
          "per sample")
    print(f"{'outsider':<18} {'taken':>6} {'drops':>6} {'late':>6} {'convicted':>10} "
          f"{'mse_steady':>11}")
    with tempfile.TemporaryDirectory() as tmp:
        for n, (target, mode) in enumerate(placements):
            s, taken = run_once(target, mode, Path(tmp) / f"run{n}")
            name = "none" if target is None else f"{mode} -> {target}"
            print(f"{name:<18} {taken:>6} {s['drops']:>6} {s['late']:>6} "
                  f"{len(s['failures']):>10} {s['mse_steady']:>11.4f}", flush=True)
    os._exit(0)          # the outsiders' sessions hold sleeping callbacks


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=10_000, help="messages per class")
    parser.add_argument("--step-ms", type=int, default=20, help="the world's step period")
    parser.add_argument("--passes", type=int, default=2,
                        help="times the whole flood is sent (RSS must not grow pass after pass)")
    parser.add_argument("--live", action="store_true",
                        help="attack a whole `socmon up` run (evidence, then a flood on what "
                             "the monitor and the recorder read); RSS of every process")
    parser.add_argument("--attack-steps", type=int, default=500,
                        help="--live: steps of forged evidence (one of each kind a step)")
    parser.add_argument("--slow-subscriber", action="store_true",
                        help="runs with an outsider reading every key slowly, per placement")
    parser.add_argument("--steps", type=int, default=1500, help="--slow-subscriber: steps")
    parser.add_argument("--sleep-s", type=float, default=0.5,
                        help="--slow-subscriber: the outsider's sleep per sample")
    args = parser.parse_args()
    if args.slow_subscriber:
        sys.exit(slow_subscriber(args.steps, args.step_ms, args.sleep_s))
    if args.live:
        sys.exit(live(args.count, args.step_ms, args.attack_steps))
    sys.exit(main(args.count, args.step_ms, args.passes))
