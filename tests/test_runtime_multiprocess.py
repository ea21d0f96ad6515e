"""The live runtime as OS processes on loopback: up, inject, role assignment, faults.

Loopback only, ports chosen by the OS, waits on conditions with deadlines (never fixed
sleeps), children in their own process groups and always stopped at teardown.
"""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agent.protocol import wire
from agent.run.launcher import ROOT
from agent.protocol import topics
from design.closed_loop import closed_loop_for
from design.gains import save_gains
from design.scenario import load_scenario, resolve_delays
from tests.runtime_procs import DEADLINE, Deployment

pytestmark = [pytest.mark.multiprocess, pytest.mark.slow]

UP_TIMEOUT = 240.0


@pytest.fixture(scope="module")
def gains_files(tmp_path_factory):
    """paper-14: any gain (the simulator check needs no stability); paper-14-live: a gain
    the exact delayed closed loop certifies stable with delays of 3 steps."""
    folder = tmp_path_factory.mktemp("gains")
    out = {}
    for name, spec in (("paper-14", "uniform:2"), ("paper-14-live", "uniform:3")):
        s = load_scenario(name)
        rng = np.random.default_rng(0)
        G = [0.3 * rng.normal(size=(s.n, len(m))) for m in s.measure] if name == "paper-14" \
            else [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
        rho = closed_loop_for(s, G, resolve_delays(s, spec)).spectral_radius()
        path = folder / f"{name}.npz"
        save_gains(path, G, {"method": "fixed random", "rho": rho})
        out[name] = (path, G, rho)
    assert out["paper-14-live"][2] < 1
    return out


def _socmon(*argv, timeout=UP_TIMEOUT):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", *argv], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    return proc.returncode, out, err


def monitor_story(folder, lines=40) -> str:
    """The end of a run folder's monitor log (what a failing assertion shows: CI keeps no
    run folder)."""
    logs = sorted(Path(folder).glob("logs/monitor*.log"))
    return "\n".join(f"{log.name}:\n" + "\n".join(log.read_text(errors="replace")
                                                  .splitlines()[-lines:]) for log in logs)


def _processes_with(text):
    """pids whose command line contains ``text``."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if text in (d / "cmdline").read_bytes().replace(b"\0", b" ").decode():
                    pids.append(int(d.name))
            except OSError:
                pass
    return pids


@pytest.mark.parametrize("delays", ["none", "uniform:2"])
def test_up_matches_the_simulator_and_learns_the_delays(tmp_path, gains_files, delays):
    path, _, _ = gains_files["paper-14"]
    out = tmp_path / "run"
    code, stdout, stderr = _socmon("up", "paper-14", "--steps", "60", "--gains", str(path),
                                   "--seed", "7", "--delays", delays, "--out", str(out),
                                   "--check-simulator", "--json", "--step-ms", "20")
    assert code == 0, stderr
    summary = json.loads(stdout)
    for key in ("mse_steady", "steps", "agents", "drops", "late", "malformed",
                "max_rel_diff_vs_simulator"):
        assert key in summary
    assert summary["steps"] == 60 and summary["agents"] == 3
    assert summary["drops"] == 0 and summary["malformed"] == 0
    assert summary["max_rel_diff_vs_simulator"] <= 1e-9
    assert summary["simulator_compared"].startswith("estimates")
    # the monitor ran all along and convicted nobody
    assert summary["monitor"] and summary["failures"] == []
    tau = 0 if delays == "none" else 2
    assert summary["learned_delays"] == {"1": {"2": tau}, "2": {"3": tau}, "3": {"1": tau},
                                         "4": {}}
    assert summary["orphans"] == [] and set(summary["exit_status"].values()) == {0}
    for name in ("summary.json", "mse.csv", "mse.json", "mse.png", "estimates.npz"):
        assert (out / name).is_file()
    mse = np.loadtxt(out / "mse.csv", delimiter=",", skiprows=1)
    assert mse.shape == (61, 2)


def test_up_with_delays_stays_stable_where_certified(tmp_path, gains_files):
    path, G, rho = gains_files["paper-14-live"]
    s = load_scenario("paper-14-live")
    D = resolve_delays(s, "uniform:3")
    predicted = closed_loop_for(s, G, D).mse_steady(s.process_noise, s.measurement_noise)
    code, stdout, stderr = _socmon("up", "paper-14-live", "--steps", "200", "--gains", str(path),
                                   "--delays", "uniform:3", "--out", str(tmp_path / "r"),
                                   "--json", "--step-ms", "20", "--deadline-ms", "2000")
    assert code == 0, stderr
    summary = json.loads(stdout)
    assert summary["learned_delays"]["1"] == {"2": 3}
    assert summary["rho_exact"] == pytest.approx(rho)
    # one run: the tail mean of MSE is within a broad factor of the exact steady value
    assert 0.2 * predicted < summary["mse_steady"] < 5 * predicted, (summary, predicted)


def test_up_interrupted_leaves_no_process_and_no_bound_port(tmp_path, gains_files):
    proc, marker = _start_long_up(tmp_path, gains_files)
    try:
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C does in a terminal
        _, err = proc.communicate(timeout=DEADLINE)
        assert proc.returncode == 130, err
    finally:
        _kill_long_up(proc, marker)
    assert _processes_with(marker) == []
    summary = json.loads((tmp_path / "r" / "summary.json").read_text())
    assert summary["error"] == "interrupted" and summary["orphans"] == []
    for port in summary["ports"]:
        with socket.socket() as sock:  # nothing is left listening (TIME_WAIT is fine)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind(("127.0.0.1", port))
            sock.listen()


def test_a_paused_recorder_holds_back_neither_the_world_nor_the_agents(tmp_path, gains_files):
    """The recorder (``up`` itself) stopped for 3 s mid-run (SIGSTOP, 150 steps): the
    world keeps its schedule and every agent has its neighbours' estimates in time (the
    recorder's copies go with congestion control DROP), and the steps it recorded equal
    the simulator's. What it missed while stopped it says (``record_gaps``, a warning),
    and its own lapse, every token gone from its view at once, is no "NO MONITOR
    ALIVE"."""
    proc, marker = _start_long_up(tmp_path, gains_files, "--step-ms", "20", "--json",
                                  "--check-simulator", steps=400)
    try:
        os.kill(proc.pid, signal.SIGSTOP)
        try:
            time.sleep(3.0)                 # the fault itself: the recorder stopped
        finally:
            os.kill(proc.pid, signal.SIGCONT)
        stdout, err = proc.communicate(timeout=UP_TIMEOUT)
    finally:
        _kill_long_up(proc, marker)
    assert proc.returncode == 0, err
    s = json.loads(stdout)
    assert s["drops"] == 0 and s["late"] == 0 and s["sensor_missed"] == 0, s["warnings"]
    assert s["max_rel_diff_vs_simulator"] <= 1e-9 and s["steps"] == 400
    # the steps it missed (when its links' leases ran out, the others dropped its copies;
    # before, zenoh and the sockets hold them) are said, not filled in; its own lapse is
    # no monitor's absence
    mse_steps = json.loads((tmp_path / "r" / "mse.json").read_text())["step"]
    missed = {k for a, b in s["record_gaps"] for k in range(a, b + 1)}
    assert missed.isdisjoint(mse_steps) and len(missed) + len(mse_steps) == 401
    assert bool(missed) == any(w.startswith("the record misses steps") for w in s["warnings"])
    assert s["no_monitor"] == [] and not any("NO MONITOR" in w for w in s["warnings"])
    assert s["diverged_at"] is None
    world = _read(tmp_path / "r" / "logs" / "world.log")
    assert "behind the schedule at step" not in world      # never re-based: not held back
    assert "done after step 400" in world


def _kill_long_up(proc, marker) -> None:
    """Whatever a test of a long ``up`` left: its process group and every child of its run."""
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
    for pid in _processes_with(marker):
        os.kill(pid, signal.SIGKILL)


def _start_long_up(tmp_path, gains_files, *extra, steps=100000):
    """Start a long ``socmon up`` in its own session; return once its clock has started.

    Returns the process and the run's marker (part of every child's command line).
    """
    path, _, _ = gains_files["paper-14-live"]
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = tmp_path / "r"
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "up", "paper-14-live",
                             "--steps", str(steps), "--gains", str(path), "--out", str(out),
                             *extra],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        deadline = time.monotonic() + DEADLINE
        # the clock has started once the world says so in its log
        while "clock starts" not in _read(out / "logs" / "world.log"):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the run did not start"
            time.sleep(0.1)
    except BaseException:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise
    return proc, f"up{proc.pid}x"


def _read(path):
    try:
        return path.read_text()
    except OSError:
        return ""


# ---------------------------------------------------------------------------------
# a deployment started by hand, driven from the test process


@pytest.fixture
def deployment(tmp_path, gains_files):
    path, _, _ = gains_files["paper-14-live"]
    deps = []

    def start(**kwargs):
        dep = Deployment(tmp_path, "paper-14-live", path, n=14, **kwargs)
        deps.append(dep)
        return dep

    yield start
    for dep in deps:
        dep.close()


def test_partitioned_link_shows_as_drops(deployment):
    dep = deployment(deadline_ms=200)  # long enough that scheduling hiccups drop nothing
    dep.wait_for(lambda: all(dep.step_of(a) >= 10 for a in (1, 2, 3)), "10 steps")
    assert dep.status[1]["drops"] == 0
    r = dep.socmon("inject", "partition", "2", "1", "on")
    assert r.returncode == 0, r.stderr
    dep.wait_for(lambda: dep.status[1]["drops"] >= 10, "drops on link 2 -> 1")
    assert dep.status[1]["links"] == {"2": {"partition": True}}
    r = dep.socmon("inject", "partition", "2", "1", "off")
    assert r.returncode == 0, r.stderr
    dep.wait_for(lambda: dep.status[1]["links"] == {}, "the partition is lifted")
    # agent 1 fell behind while waiting out deadlines; once past the stamps agent 2 sent
    # during the partition, nothing more is dropped
    k2 = dep.step_of(2)
    dep.wait_for(lambda: dep.step_of(1) > k2 + 5, "agent 1 catches up")
    stopped = dep.status[1]["drops"]
    k = dep.step_of(1)
    dep.wait_for(lambda: dep.step_of(1) >= k + 20, "20 more steps")
    assert dep.status[1]["drops"] <= stopped + 2  # the link is back


def test_injected_delay_is_learned_while_running(deployment):
    dep = deployment(deadline_ms=40)
    dep.wait_for(lambda: dep.step_of(1) >= 5, "5 steps")
    r = dep.socmon("inject", "delay", "3", "2", "--steps", "4")
    assert r.returncode == 0, r.stderr
    dep.wait_for(lambda: dep.status[2]["delays"] == {3: 4}, "agent 2 learns delay 4 from 3")
    assert dep.status[1]["delays"] == {2: 0}
    # a link the receiver does not listen on is applied, and said to change nothing now
    r = dep.socmon("inject", "delay", "1", "2", "--steps", "1")
    assert r.returncode == 0, r.stderr
    assert "warning: agent 2 does not listen to agent 1 in its current role (it listens " \
           "to 3)" in r.stderr
    # an agent that is not there is said at once, with the ones that are
    r = dep.socmon("inject", "drop", "1", "9", "0.5", "--timeout", "60", timeout=30)
    assert r.returncode == 1
    assert "agent 9 is not alive" in r.stderr and "the agents alive are 1, 2, 3, 4" in r.stderr


def test_malformed_flood_leaves_the_agent_running_and_counted(deployment):
    dep = deployment()
    dep.wait_for(lambda: dep.step_of(1) >= 5, "5 steps")
    base = dep.status[1]["malformed"]
    rng = np.random.default_rng(0)
    n = 14
    good_est = wire.encode_est(2, 3, np.zeros(n), 0, 0.0)
    kinds = [
        lambda: rng.bytes(int(rng.integers(0, 50))),                      # garbage
        lambda: b"\xc1",                                                  # invalid msgpack
        lambda: b"\x93\x01\x02\x03",                                      # not a map
        lambda: good_est.replace(b"\xa1v\x01", b"\xa1v\x07"),             # unknown version
        lambda: wire.encode_est(2, 3, np.zeros(5), 0, 0.0),               # wrong shape
        lambda: wire.encode_est(2, 3, np.full(n, np.nan), 0, 0.0),        # NaN
        lambda: wire.encode_est(77, 3, np.zeros(n), 0, 0.0),              # unknown sender
        lambda: wire.encode_est(2, 2**37, np.zeros(n), 0, 0.0),           # stamp far ahead
        lambda: wire.encode_sensors(5, np.full(n, np.inf)),               # inf readings
        lambda: wire.encode_ctl(1, 1, 10, ["7"], {2: 0.5}, 0.5, np.zeros((3, 1))),  # shape
    ]
    targets = [topics.est_key(dep.run, 2), topics.ctl_key(dep.run, 1), topics.impair_key(dep.run),
               topics.sensors_key(dep.run)]
    for t in targets:
        dep.peer.publisher(t, block=True)
    total = 1000
    for i in range(total):
        payload = kinds[i % len(kinds)]()
        dep.peer.put(targets[i % len(targets)], payload)
    dep.wait_for(lambda: dep.status[1]["malformed"] - base >= total,
                 "agent 1 counts 1000 malformed messages")
    k = dep.step_of(1)
    dep.wait_for(lambda: dep.step_of(1) >= k + 10, "agent 1 keeps stepping")
    reasons = dep.status[1]["malformed_reasons"]
    assert len(reasons) >= 5, reasons
    assert dep.children.children["agent-1"].returncode is None


def test_role_assignment_switches_measured_node_at_the_stated_step(deployment):
    dep = deployment()
    dep.wait_for(lambda: dep.step_of(1) >= 5, "5 steps")
    at = dep.step_of(1) + 25
    ctl = topics.ctl_key(dep.run, 1)
    dep.peer.publisher(ctl, block=True)
    payload = wire.encode_ctl(1, 1, at, ["8"], {2: 0.5}, 0.5, np.full((14, 1), 0.1))
    dep.peer.put(ctl, payload)
    dep.wait_for(lambda: dep.status[1]["ctl"]["accepted"] == 1 or
                 dep.step_of(1) >= at - 5, "the assignment is accepted")
    assert dep.status[1]["ctl"]["accepted"] == 1, dep.status[1]["ctl"]
    dep.wait_for(lambda: dep.status[1]["epoch"] == 1 and (1, at) in dep.est_epochs,
                 "the new role is active")
    assert dep.status[1]["measure"] == ["8"]
    assert dep.est_epochs[(1, at - 1)] == 0 and dep.est_epochs[(1, at)] == 1
    # an older epoch is rejected
    dep.peer.put(ctl, payload)
    dep.wait_for(lambda: dep.status[1]["ctl"]["rejected"] == 1, "the stale epoch is rejected")
    assert "not newer" in dep.status[1]["ctl"]["last_error"]


def test_standby_agent_takes_a_role(deployment):
    dep = deployment()
    dep.wait_for(lambda: dep.step_of(4) >= 5, "5 steps")
    assert dep.status[4]["active"] is False
    at = dep.step_of(4) + 25
    ctl = topics.ctl_key(dep.run, 4)
    dep.peer.publisher(ctl, block=True)
    dep.peer.put(ctl, wire.encode_ctl(4, 1, at, ["8"], {1: 0.5}, 0.5, np.full((14, 1), 0.1),
                                      take_over=1))
    dep.wait_for(lambda: (4, at + 3) in dep.est_epochs and dep.status[4]["active"],
                 "the standby agent publishes")
    # it publishes the estimate it took over stamped at - 1, then computes from step at
    assert (4, at - 2) not in dep.est_epochs and dep.est_epochs[(4, at - 1)] == 1
    assert dep.est_epochs[(4, at)] == 1


def test_sigkill_of_an_agent_does_not_hang_the_others(deployment):
    # a deadline of a minute: only the lost liveliness of agent 3 can unblock agent 2
    dep = deployment(deadline_ms=60000)
    dep.wait_for(lambda: all(dep.step_of(a) >= 5 for a in (1, 2, 3)), "5 steps")
    os.killpg(dep.children.children["agent-3"].proc.pid, signal.SIGKILL)
    k = {a: dep.step_of(a) for a in (1, 2)}
    deadline = time.monotonic() + DEADLINE
    while not all(dep.step_of(a) >= k[a] + 30 for a in (1, 2)):
        assert time.monotonic() < deadline, "agents 1 and 2 stopped stepping"
        dep.read()
        dep.children.reap()
        assert dep.children.children["agent-1"].returncode is None
        assert dep.children.children["agent-2"].returncode is None
        dep.peer.wait(timeout=0.1)
    assert dep.status[2]["drops"] >= 1  # agent 2 listens to agent 3


def test_up_without_monitor_stops_everything_when_a_child_dies(tmp_path, gains_files):
    """Without the monitor nobody can replace a dead agent: up stops the run (with the
    monitor a dead agent is an event: tests/test_monitor_multiprocess.py)."""
    proc, marker = _start_long_up(tmp_path, gains_files, "--json", "--no-monitor")
    try:
        victim = [pid for pid in _processes_with(marker)
                  if " --id 2 " in Path(f"/proc/{pid}/cmdline").read_bytes()
                  .replace(b"\0", b" ").decode()]
        assert len(victim) == 1
        os.kill(victim[0], signal.SIGKILL)
        stdout, err = proc.communicate(timeout=DEADLINE)
        assert proc.returncode == 1, err
        assert "agent-2 exited with status -9" in err
    finally:
        _kill_long_up(proc, marker)
    assert _processes_with(marker) == []
    summary = json.loads(stdout)
    assert summary["orphans"] == [] and summary["exit_status"]["agent-2"] == -9
