"""``socmon watch`` on a run started by hand and on an ``up`` run; ``inject --attach``.

Loopback only, ports from ``listen_port()``, waits on conditions with deadlines, children
in their own process groups (``agent.run.launcher.Children``), always stopped.
"""

import csv
import json
import os
import re
import signal
import time

import numpy as np
import pytest

from broker_free_net.ports import listen_port
from design.closed_loop import closed_loop_for
from design.gains import load_gains
from design.scenario import load_scenario
from design.simulate import simulate

pytestmark = [pytest.mark.multiprocess]

DEADLINE = 90.0   # a loaded 2-core machine


@pytest.fixture(scope="module")
def live_run(live_gains):
    """paper-14-live, its fixed gains and their file (tests/conftest.py)."""
    return load_scenario("paper-14-live"), list(load_gains(live_gains).G), live_gains


def _wait(predicate, what, children, timeout=DEADLINE, allowed_exit=()):
    deadline = time.monotonic() + timeout
    while not predicate():
        dead = [c.name for c in children.reap()
                if c.returncode is not None and c.name not in allowed_exit]
        if dead:
            raise AssertionError(f"{dead} exited while waiting for {what}:\n"
                                 + "\n".join(children.tail(n, 20) for n in dead))
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.05)


def _log(children, name):
    return children.children[name].log_path.read_text(errors="replace")


def _watched_step(children, name):
    steps = re.findall(r"^run \S+  step (-?\d+)", _log(children, name), re.M)
    return int(steps[-1]) if steps else None


def _mse_csv(path):
    rows = list(csv.reader(open(path)))[1:]
    return np.array([int(r[0]) for r in rows]), np.array([float(r[1]) for r in rows])


def test_watch_records_a_hand_started_run(tmp_path, children, live_run):
    """World (no --steps: it runs until stopped, like the compose file's) and agents started
    by hand as docs/runtime.md says; ``watch --out`` ended by SIGTERM writes the run folder,
    whose MSE is the one of the simulator (same seed and gains; nothing dropped) and the
    one of the truth and estimates it saved."""
    s, G, gains = live_run
    run = f"w{os.getpid()}"
    ep = [f"tcp/127.0.0.1:{listen_port()}" for _ in range(s.N + s.standby + 1)]
    common = ["--run", run, "--seed", "3"]
    children.start("world", ["world", "paper-14-live", *common, "--listen", ep[0],
                             "--step-ms", "20"])
    out = tmp_path / "watched"
    children.start("watch", ["watch", "paper-14-live", "--run", run, "--connect", ep[0],
                             "--gains", str(gains), "--delays", "none", "--seed", "3",
                             "--out", str(out), "--interval", "0.1"])
    # the watcher's first view is shown once its subscriptions are declared
    _wait(lambda: _watched_step(children, "watch") is not None, "the watcher", children)
    for a in range(1, s.N + s.standby + 1):
        argv = ["agent", "paper-14-live", "--id", str(a), *common, "--listen", ep[a],
                "--connect", ep[0], "--delays", "none", "--deadline-ms", "30000"]
        if a <= s.N:
            argv += ["--gains", str(gains)]
        children.start(f"agent-{a}", argv)
    _wait(lambda: (_watched_step(children, "watch") or -1) >= 80, "step 80 watched", children)
    # a second agent 2 and a second world started by mistake: each is refused, naming the
    # session that holds its id, and publishes nothing (the MSE below is the simulator's)
    children.start("agent-2-again", ["agent", "paper-14-live", "--id", "2", *common,
                                     "--connect", ep[0], "--gains", str(gains)])
    children.start("world-again", ["world", "paper-14-live", *common, "--connect", ep[0]])
    again = ("agent-2-again", "world-again")
    _wait(lambda: all(children.children[n].returncode is not None for n in again),
          "the second agent 2 and world to be refused", children, allowed_exit=again,
          timeout=30)
    for name, who in zip(again, ("agent 2", "world 0")):
        assert children.children[name].returncode == 1, _log(children, name)
        assert f"socmon: {who} of run {run} is already running (session " in \
            _log(children, name)
    refused_at = _watched_step(children, "watch")
    _wait(lambda: (_watched_step(children, "watch") or -1) >= refused_at + 20,
          "20 steps after", children, allowed_exit=again)
    os.killpg(children.children["watch"].proc.pid, signal.SIGTERM)
    _wait(lambda: children.children["watch"].returncode is not None, "the watch to end",
          children, allowed_exit=("watch", *again))   # mse.png: matplotlib is slow when loaded
    assert children.children["watch"].returncode == 130, _log(children, "watch")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ended"] == "interrupted" and summary["run"] == run
    steps, mse = _mse_csv(out / "mse.csv")
    assert steps[0] == 0 and np.array_equal(steps, np.arange(len(steps))) and steps[-1] >= 80
    # the MSE the world's truth and the agents' estimates give (estimates.npz)...
    saved = np.load(out / "estimates.npz")
    assert list(saved["agents"]) == [1, 2, 3]       # the standby publishes no estimate
    own = ((saved["estimates"] - saved["truth"][:, None, :]) ** 2).mean(axis=2).mean(axis=1)
    np.testing.assert_allclose(mse, own[: len(mse)], rtol=1e-12)
    # ... equals the simulator's with the same seed and gains, step by step
    sim = simulate(s, G, steps=int(steps[-1]), trials=1, seed=3,
                   delays=np.zeros((s.N, s.N), int)).mse_trials[0]
    np.testing.assert_allclose(mse, sim[steps], rtol=1e-9)
    loop = closed_loop_for(s, G, np.zeros((s.N, s.N), int))
    assert summary["mse_steady_exact"] == pytest.approx(
        loop.mse_steady(s.process_noise, s.measurement_noise), rel=1e-12)
    assert summary["drops"] == 0 and summary["recorder_malformed"] == 0


def test_a_watch_whose_world_is_killed_says_it_lost_it_and_exits_1(tmp_path, children,
                                                                  live_run):
    """The world SIGKILLed mid-run: its token goes without its end message. The watch
    ends once the agents stop publishing, says it lost the world (exit 1, ``ended: world
    lost``, a warning), not that the run "ended with its world"."""
    s, G, gains = live_run
    run = f"wl{os.getpid()}"
    ep = [f"tcp/127.0.0.1:{listen_port()}" for _ in range(s.N + 1)]
    common = ["--run", run, "--seed", "3"]
    children.start("world", ["world", "paper-14-live", *common, "--listen", ep[0],
                             "--step-ms", "20", "--wait-agents", "1,2,3"])
    out = tmp_path / "watched"
    children.start("watch", ["watch", "paper-14-live", "--run", run, "--connect", ep[0],
                             "--gains", str(gains), "--delays", "none", "--seed", "3",
                             "--out", str(out), "--interval", "0.1"])
    _wait(lambda: _watched_step(children, "watch") is not None, "the watcher", children)
    for a in range(1, s.N + 1):
        children.start(f"agent-{a}", ["agent", "paper-14-live", "--id", str(a), *common,
                                      "--listen", ep[a], "--connect", ep[0], "--delays",
                                      "none", "--gains", str(gains)])
    _wait(lambda: (_watched_step(children, "watch") or -1) >= 60, "step 60 watched", children)
    os.killpg(children.children["world"].proc.pid, signal.SIGKILL)
    _wait(lambda: children.children["watch"].returncode is not None, "the watch to end",
          children, allowed_exit=("watch", "world"))
    log = _log(children, "watch")
    assert children.children["watch"].returncode == 1, log
    assert f"paper-14-live: run {run} LOST ITS WORLD (its token went without its end" in log
    assert "warning: the world left after step " in log      # the warnings, as up says them
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ended"] == "world lost" and summary["steps"] >= 60
    assert any(w.startswith("the world left after step ") for w in summary["warnings"])
    # the world started again by hand: it cannot take over a run under way, and says so
    # at once instead of waiting its start timeout for agents that will never be "ready"
    children.start("world-again", ["world", "paper-14-live", *common, "--connect", ep[1],
                                   "--step-ms", "20", "--wait-agents", "1,2,3"])
    _wait(lambda: children.children["world-again"].returncode is not None,
          "the world started again to give up", children, timeout=30,
          allowed_exit=("watch", "world", "world-again"))
    assert children.children["world-again"].returncode == 1
    assert f"of run {run} are at step " in _log(children, "world-again")
    assert "a world cannot join a run under way" in _log(children, "world-again")


def test_hand_started_processes_with_another_seed_or_gains_are_named(tmp_path, children,
                                                                    live_run):
    """By hand, agent 2 started with another --seed and agent 3 with another gains file:
    the world names agent 2 (its noise is not the run's), the monitor names agent 3 (its
    predictions assume its own gains), each once, and nobody else."""
    from design.gains import load_gains, save_gains

    s, G, gains = live_run
    other = tmp_path / "other.npz"
    save_gains(other, [g if i != 2 else 0.9 * g for i, g in enumerate(G)],
               dict(load_gains(gains).meta))
    run = f"ws{os.getpid()}"
    ep = [f"tcp/127.0.0.1:{listen_port()}" for _ in range(s.N + s.standby + 2)]
    common = ["--run", run, "--seed", "3"]
    children.start("world", ["world", "paper-14-live", *common, "--listen", ep[0],
                             "--step-ms", "20", "--steps", "40", "--wait-monitor", "1"])
    children.start("monitor", ["monitor", "paper-14-live", *common, "--gains", str(gains),
                               "--listen", ep[-1], "--connect", ep[0]])
    for a in range(1, s.N + s.standby + 1):
        argv = ["agent", "paper-14-live", "--id", str(a), *common, "--listen", ep[a],
                "--connect", ep[0]]
        if a == 2:
            argv[argv.index("--seed") + 1] = "4"
        if a <= s.N:
            argv += ["--gains", str(other if a == 3 else gains)]
        children.start(f"agent-{a}", argv)
    _wait(lambda: children.children["world"].returncode is not None, "the world's 40 steps",
          children, timeout=180, allowed_exit=("world",))
    world = _log(children, "world")
    assert children.children["world"].returncode == 0, world
    warned = [line for line in world.splitlines() if "warning" in line]
    assert warned == ["world: warning: agent 2 was started with --seed 4, this world with "
                      "--seed 3: its measurement noise and first estimate are not the run's "
                      "(a replay differs)"]
    _wait(lambda: "warning: agent" in _log(children, "monitor"), "the monitor's warning",
          children, allowed_exit=("world", "monitor", *(f"agent-{a}" for a in range(1, 5))))
    warned = [line for line in _log(children, "monitor").splitlines() if "warning" in line]
    assert len(warned) == 1 and warned[0].startswith(
        "monitor 1: warning: agent 3 was started with another gain than this monitor's"), warned


@pytest.mark.parametrize("secure", [False, True], ids=["tcp", "secure"])
def test_up_run_attached_by_inject_and_watch(tmp_path, children, live_run, secure):
    """``up --run --listen`` writes run.json; ``inject --attach`` reaches the run (signed
    with the folder's operator key, as the agents require; with the run's keys when it is
    secure); ``watch --attach`` records the same MSE and failure as ``up`` itself."""
    s, G, gains = live_run
    up_dir, watch_dir = tmp_path / "up", tmp_path / "watched"
    listen = f"{'tls' if secure else 'tcp'}/127.0.0.1:{listen_port()}"
    children.start("up", ["up", "paper-14-live", "--steps", "300", "--step-ms", "20",
                          "--gains", str(gains), "--run", "attachme", "--listen", listen,
                          "--kill", "150:2", "--out", str(up_dir)]
                   + (["--secure"] if secure else []))
    _wait(lambda: (up_dir / "run.json").exists(), "run.json", children)
    info = json.loads((up_dir / "run.json").read_text())
    assert info["run"] == "attachme" and info["connect"] == listen
    assert info["operator_key"] == str((up_dir / "operator.key").resolve())
    assert info["keys"] == (str((up_dir / "keys").resolve()) if secure else None)
    assert set(info["processes"]) >= {"recorder", "world", "agent-1", "monitor-1"}
    assert all("pid" in p for n, p in info["processes"].items() if n != "recorder")
    children.start("watch", ["watch", "--attach", str(up_dir), "--out", str(watch_dir),
                             "--json"])
    children.start("inject", ["inject", "delay", "3", "1", "--steps", "2",
                              "--attach", str(up_dir)])
    _wait(lambda: children.children["inject"].returncode is not None, "inject", children,
          allowed_exit=("inject",))
    assert children.children["inject"].returncode == 0, _log(children, "inject")
    assert "delay applied on link 3 -> 1" in _log(children, "inject")
    if not secure:
        # without the run's operator key: agent 1 refuses the change, and inject says so
        children.start("unsigned", ["inject", "drop", "3", "1", "0.5", "--run",
                                    "attachme", "--connect", listen])
        _wait(lambda: children.children["unsigned"].returncode is not None, "unsigned",
              children, allowed_exit=("inject", "unsigned"))
        assert children.children["unsigned"].returncode == 1, _log(children, "unsigned")
        assert "agent 1 refused the change (" in _log(children, "unsigned")
        assert "sign it with the run's operator key" in _log(children, "unsigned")
    _wait(lambda: all(children.children[n].returncode is not None for n in ("up", "watch")),
          "up and watch to end", children, timeout=180,
          allowed_exit=("up", "watch", "inject", "unsigned"))
    assert children.children["up"].returncode == 0, _log(children, "up")
    assert children.children["watch"].returncode == 0, _log(children, "watch")
    up = json.loads((up_dir / "summary.json").read_text())
    lines = [json.loads(x) for x in _log(children, "watch").splitlines() if x.startswith("{")]
    assert lines[-1]["kind"] == "summary" and {x["kind"] for x in lines[:-1]} == {"view"}
    watched = json.loads((watch_dir / "summary.json").read_text())
    assert watched["ended"] == "world ended" and watched["steps"] == up["steps"] == 300
    assert watched["mse_steady"] == up["mse_steady"]
    assert watched["mse_steady_exact"] == up["mse_steady_exact"]
    assert watched["mse_steady_exact_in_force"] == up["mse_steady_exact_in_force"]
    # the monitors leave with the world: no window without a monitor, as up reads it
    assert watched.get("no_monitor") == up.get("no_monitor")
    assert not [w for w in watched.get("warnings", []) if "NO MONITOR" in w]
    # the same conviction (a kill is usually `crash`; on a loaded machine the loop can be
    # seen stalled for the hang timeout before the token goes: `hang`)
    assert [(f["agent"], f["cause"]) for f in watched["failures"]] == \
        [(f["agent"], f["cause"]) for f in up["failures"]]
    assert [(f["agent"], f["cause"] in ("crash", "hang")) for f in up["failures"]] == [(2, True)]
    assert watched["rosters"] == up["rosters"]
    k_up, m_up = _mse_csv(up_dir / "mse.csv")
    k_w, m_w = _mse_csv(watch_dir / "mse.csv")
    common = np.intersect1d(k_up, k_w)
    assert len(common) >= 250
    np.testing.assert_array_equal(m_up[np.isin(k_up, common)], m_w[np.isin(k_w, common)])
