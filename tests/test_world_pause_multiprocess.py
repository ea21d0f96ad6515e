"""A paused world is a fault, not an end; a child that dies before the clock starts ends
the start at once. Loopback only, deadlines, children in their own process groups."""

import argparse
import json
import re

import pytest

from agent.run.local import LocalRun
from tests.test_runtime_multiprocess import _socmon, monitor_story

pytestmark = [pytest.mark.multiprocess]


def _config(tmp_path, gains, steps, **extra):
    from agent.run.setup import run_config

    args = argparse.Namespace(
        scenario="paper-14-live", steps=steps, gains=str(gains), seed=0, out=str(tmp_path),
        delays="scenario", step_ms=None, deadline_ms=None, start_timeout=60.0, quiet=True,
        no_monitor=False, drop=0.0, kill=[], stop=[], kill_monitor=None, hang_timeout=1.0,
        hang_timeout_max=5.0,
        check_simulator=False, **extra)
    return run_config(args, lambda text: None)


def test_a_child_that_dies_before_the_clock_starts_ends_the_start(tmp_path, live_gains):
    class BadAgent(LocalRun):
        def _argv(self, rec, ep):
            argv = super()._argv(rec, ep)
            argv["agent-2"] = ["agent", "no-such-scenario", "--id", "2"]   # exits 2 at once
            return argv

    rec = BadAgent(_config(tmp_path, live_gains, 50)).run()
    assert re.match(r"agent-2 exited with status 2 before the clock started; its log "
                    r"ends:\n.*no-such-scenario", rec.failure or "", re.S), rec.failure
    assert not rec.truth


def _up(tmp_path, gains, *argv):
    return _socmon("up", "paper-14-live", "--gains", str(gains), "--out", str(tmp_path),
                   "--json", "--quiet", *argv)


def test_a_world_paused_past_the_lease_is_waited_for_and_the_run_completes(tmp_path,
                                                                          live_gains):
    """SIGSTOP of the world for 3 s (three link leases): its token goes without its end.
    The agents and the monitor wait for it, nobody is convicted, the world re-bases its
    clock instead of publishing the missed steps at once, and the run completes."""
    code, out, err = _up(tmp_path, live_gains, "--steps", "300",
                         "--fault", "worldstop:100::3")
    assert code == 0, err
    summary = json.loads(out)
    assert summary["failures"] == []
    logs = tmp_path / "logs"
    assert "the clock is re-based" in (logs / "world.log").read_text()
    monitor = (logs / "monitor-1.log").read_text()
    assert "without its end" in monitor and "the world is back" in monitor
    assert "verdict:" not in monitor
    for a in (1, 2, 3, 4):
        log = (logs / f"agent-{a}.log").read_text()
        assert "the world went silent" in log and "giving up" not in log


@pytest.mark.parametrize("seconds", [1, 5, pytest.param(30, marks=pytest.mark.slow)])
def test_a_paused_monitor_stays_and_recovers_a_crash_after_it(tmp_path, live_gains, seconds):
    """SIGSTOP of the monitor (its links lapse: every token seems to go at once): it
    resumes, rebuilds from the network and still answers a crash that comes after."""
    kill = 400 + 50 * seconds          # 20 ms steps: well after the monitor resumed
    code, out, err = _up(tmp_path, live_gains, "--steps", str(kill + 200),
                         "--fault", f"monitorstop:100::{seconds}", "--kill", f"{kill}:1")
    assert code == 0, (err, monitor_story(tmp_path))
    summary = json.loads(out)
    failures = summary["failures"]
    assert [(f["agent"], f["cause"]) for f in failures] == [(1, "crash")], \
        (failures, monitor_story(tmp_path))
    assert failures[0]["replacement"]["agent"] == 4 and summary["recovered"] is True
    monitor = (tmp_path / "logs" / "monitor-1.log").read_text()
    assert "monitor paused" in monitor and "exiting" not in monitor.split("verdict")[0]


def test_with_no_monitor_alive_a_crash_is_reported_undetected_and_unrecovered(tmp_path,
                                                                            live_gains):
    """Every monitor SIGKILLed for good, then agent 1 killed: nobody convicts it. The run
    says so (a warning, ``no_monitor``), records the crash as an undetected, unrecovered
    failure of an agent holding a role, and exits 1."""
    code, out, err = _up(tmp_path, live_gains, "--steps", "500",
                         "--fault", "monitorsgone:100", "--fault", "kill:300:1")
    assert code == 1, err
    summary = json.loads(out)
    assert summary["recovered"] is False
    [f] = summary["failures"]
    assert (f["agent"], f["detected"], f["role"], f["why"]) == (1, False, "active",
                                                                "no monitor alive")
    assert f["died_step"] >= 300 and f["detected_step"] is None
    [window] = summary["no_monitor"]
    assert 100 <= window["from"] <= f["died_step"] and window["to"] is None
    assert "NO MONITOR ALIVE from step" in err and "never convicted" in err
    events = [json.loads(x) for x in (tmp_path / "events.jsonl").read_text().splitlines()]
    assert not [e for e in events if e.get("kind") == "verdict"]


def test_a_killed_active_monitor_hands_over_and_a_crash_after_it_is_recovered(tmp_path,
                                                                               live_gains):
    """SIGKILL of the active monitor (started again at once) with the standby beside it:
    one of them acts, and a crash that comes after is convicted once and recovered."""
    code, out, err = _up(tmp_path, live_gains, "--steps", "600",
                         "--fault", "monitor:100", "--kill", "300:1")
    assert code == 0, err
    summary = json.loads(out)
    assert [(f["agent"], f["cause"]) for f in summary["failures"]] == [(1, "crash")]
    assert summary["recovered"] is True and summary["rosters"][-1]["ids"] == [4, 2, 3]
    assert summary.get("no_monitor") == []


@pytest.mark.chaos
def test_a_world_silent_until_the_agents_leave_ends_the_run_with_its_reason(tmp_path,
                                                                             live_gains):
    """SIGSTOP of the world for 70 s, past Timing.world_silent_s (60 s): up says the world
    is silent, the agents leave it, and the run ends there with exit 1, the step and the
    silence in the summary, and no agent called dead or the run diverged (long: under the
    chaos marker)."""
    code, out, err = _up(tmp_path, live_gains, "--steps", "300",
                         "--fault", "worldstop:100::70")
    assert code == 1, err
    summary = json.loads(out)
    assert summary["world_silent"]["step"] >= 99 and summary["world_silent"]["seconds"] > 59
    assert "the world went silent after step" in summary["error"]
    assert summary["failures"] == [] and summary.get("diverged_at") is None, summary
