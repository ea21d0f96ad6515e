"""docs/runtime.md's recipe for starting a run by hand runs as written (monitor included),
with free loopback ports in place of the documented ones and a shorter run."""

import os
import re
import shlex
import signal
import subprocess
import sys
import time

import pytest

from agent.run.launcher import ROOT
from broker_free_net.ports import listen_port

pytestmark = [pytest.mark.multiprocess]

DEADLINE = 240.0


def _recipe() -> list:
    text = (ROOT / "docs" / "runtime.md").read_text()
    section = text.split("## Running one process per agent by hand", 1)[1]
    block = section.split("```", 2)[1]
    return [line.strip() for line in block.splitlines() if line.strip().startswith("socmon ")]


def test_the_documented_recipe_runs_a_whole_run_and_every_process_says_what_it_waits_for(
        tmp_path):
    lines = _recipe()
    assert lines[0].startswith("socmon design") and any(" monitor " in x for x in lines)
    ports = sorted({int(p) for p in re.findall(r"127\.0\.0\.1:(\d+)", "\n".join(lines))})
    free = {}
    for p in ports:
        port = listen_port()
        while port in free.values():
            port = listen_port()
        free[p] = port
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    procs = {}

    def argv(line):
        line = re.sub(r"127\.0\.0\.1:(\d+)", lambda m: f"127.0.0.1:{free[int(m.group(1))]}",
                      line)
        line = line.replace("--steps 1500", "--steps 300")
        return [sys.executable, "-m", "agent.cli", *shlex.split(line)[1:]]

    design = subprocess.run(argv(lines[0]), cwd=tmp_path, env=env, capture_output=True,
                            text=True, timeout=DEADLINE)
    assert design.returncode == 0, design.stderr
    try:
        for line in lines[1:]:
            words = shlex.split(line)
            name = words[1] + ("-" + words[words.index("--id") + 1] if "--id" in words else "")
            log = open(tmp_path / f"{name}.log", "w")
            procs[name] = subprocess.Popen(argv(line), cwd=tmp_path, env=env, stdout=log,
                                           stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline and any(p.poll() is None for p in procs.values()):
            time.sleep(0.2)
        codes = {name: p.poll() for name, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    logs = {name: (tmp_path / f"{name}.log").read_text() for name in procs}
    assert codes == {name: 0 for name in procs}, (codes, logs)
    assert "waiting for agents [1, 2, 3, 4]" in logs["world"]
    assert "done after step 300" in logs["world"]
    for a in (1, 2, 3):
        assert "ready (every agent heard)" in logs[f"agent-{a}"]
        assert "clock started at step 0; measures" in logs[f"agent-{a}"]
    assert "clock started at step 0; standby" in logs["agent-4"]
    assert "active" in logs["monitor"] and "the world ended after step 300" in logs["monitor"]


def test_a_monitor_started_by_hand_warns_of_a_diverging_gap_as_up_does(tmp_path):
    """Gains designed without the gap terms leave agent 3's gap diverging (tests/test_gap.py):
    the first monitor says so at its start, before it joins a run."""
    from agent.run.launcher import Children
    from tests.waiting import wait_until

    env = dict(os.environ, PYTHONPATH=str(ROOT))
    gains = tmp_path / "g.npz"
    design = subprocess.run(
        [sys.executable, "-m", "agent.cli", "design", "paper-14-live", "--delays", "uniform:3",
         "--target", "0.95", "--starts", "2", "--max-iter", "60", "--no-gaps",
         "--out", str(gains)], cwd=tmp_path, env=env, capture_output=True, text=True,
        timeout=DEADLINE)
    assert design.returncode == 0, design.stderr
    children = Children(tmp_path / "logs")
    try:
        children.start("monitor", ["monitor", "paper-14-live", "--run", "gapwarn", "--gains",
                                   str(gains), "--delays", "uniform:3", "--prepare-s", "2",
                                   "--listen", f"tcp/127.0.0.1:{listen_port()}"])
        log = tmp_path / "logs" / "monitor.log"
        assert wait_until(lambda: "watching run gapwarn" in log.read_text(), DEADLINE), \
            log.read_text()
        text = log.read_text()
        assert "monitor 1: warning: agent 3 fails: the others run a loop of exact radius" \
            in text, text
        assert text.index("warning: agent 3 fails") < text.index("watching run gapwarn")
    finally:
        children.stop_all(grace=5.0)
