"""What a user sees when something is wrong: one-line errors naming the flag (exit 2), gains
of another scenario refused, a closed pipe handled once, warnings carried to the summary."""

import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from agent.cli.main import EXIT_BROKEN_PIPE, main
from agent.run.summary import MAX_LOG_WARNINGS, log_warnings
from design.gains import gains_meta, save_gains

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def paper14_gains(paper14, paper14_design, tmp_path_factory):
    """A stabilising gain of paper-14 with paper-14's digest in its meta."""
    result = paper14_design
    path = tmp_path_factory.mktemp("g") / "g14.npz"
    save_gains(path, result.G, gains_meta(paper14, "default", paper14.delays, result.rho))
    return str(path)


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err, err
    return err


# -- gains designed for another scenario ------------------------------------------------

@pytest.mark.parametrize("command", [
    ["simulate", "paper-14-live", "--steps", "20", "--trials", "2"],
    ["certify", "paper-14-live", "--taus", "0"],
    ["up", "paper-14-live", "--steps", "5"],
    ["agent", "paper-14-live", "--id", "1"],
    ["monitor", "paper-14-live", "--run", "r"],
])
def test_gains_of_another_scenario_exit_2_naming_both(paper14_gains, command, capsys):
    from design.scenario import load_scenario

    live = load_scenario("paper-14-live")
    assert main(command + ["--gains", paper14_gains]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("socmon: --gains: ")
    assert "scenario paper-14 (digest 89e4451208cda747)" in err
    assert f"scenario paper-14-live (digest {live.digest()})" in err
    assert "--force-gains" in err


@pytest.mark.parametrize("command", [
    ["simulate", "paper-14-live", "--steps", "20", "--trials", "2"],
    ["certify", "paper-14-live", "--taus", "0"],
])
def test_force_gains_runs_with_a_warning(paper14_gains, command, capsys):
    rc = main(command + ["--gains", paper14_gains, "--force-gains"])
    err = capsys.readouterr().err
    assert rc in (0, 1)
    assert "warning: --gains:" in err and "paper-14-live" in err


def test_gains_without_a_digest_are_accepted(paper14, tmp_path, capsys):
    path = tmp_path / "hand.npz"
    save_gains(path, [np.zeros((14, 1))] * 3, {"method": "hand"})
    assert main(["certify", "paper-14-live", "--gains", str(path), "--taus", "0"]) in (0, 1)
    assert "warning" not in capsys.readouterr().err


# -- a file that is not a gains file ------------------------------------------------------

def test_png_as_gains_is_one_line_without_numpy_advice(tmp_path, capsys):
    png = tmp_path / "mse.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    assert main(["simulate", "paper-14", "--gains", str(png), "--steps", "10"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("socmon: --gains: ") and "not a .npz gains file" in err
    assert "allow_pickle" not in err


def test_npy_and_directory_as_gains(tmp_path, capsys):
    npy = tmp_path / "k.npy"
    np.save(npy, np.zeros(3))
    assert main(["certify", "paper-14", "--gains", str(npy)]) == 2
    assert "not a .npz gains file" in _one_line(capsys.readouterr().err)
    assert main(["certify", "paper-14", "--gains", str(tmp_path)]) == 2
    assert "is a directory" in _one_line(capsys.readouterr().err)


# -- --zenoh-config --------------------------------------------------------------------------

@pytest.mark.parametrize("command", [
    ["world", "paper-14", "--steps", "5"],
    ["agent", "paper-14", "--id", "1"],
    ["monitor", "paper-14", "--run", "r"],
    ["inject", "clear-all", "--connect", "tcp/127.0.0.1:9"],
])
def test_zenoh_config_malformed_or_missing(paper14_gains, command, tmp_path, capsys):
    if command[0] in ("agent", "monitor"):
        command = command + ["--gains", paper14_gains]
    bad = tmp_path / "bad.json5"
    bad.write_text('{ mode: "peer", listen: { endpoints: [\n')
    assert main(command + ["--zenoh-config", str(bad)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"socmon: --zenoh-config: cannot load {str(bad)!r}: line "), err
    missing = tmp_path / "none.json5"
    assert main(command + ["--zenoh-config", str(missing)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err == f"socmon: --zenoh-config: no such file {str(missing)!r}\n"


# -- a reader that goes away --------------------------------------------------------------

def test_closed_stdout_ends_quietly():
    """``socmon analyze --json | head -0``: no traceback, the SIGPIPE status."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "agent.cli", "analyze", "paper-14", "--json"],
                            cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()              # the reader is gone before the first write
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=120) == EXIT_BROKEN_PIPE
    assert err == "", err


# -- a stop signal while the process exits ---------------------------------------------------

_SLOW_EXIT = """
import signal, sys, time
import agent.cli.main as cli
signal.signal(signal.SIGTERM, lambda *_: None)   # as the world and the agents do
cli.main = lambda: 3                               # the command's work is done

class SlowToFinalize:                              # like zenoh's runtime, torn down last
    def __del__(self):
        print("exiting", flush=True)
        time.sleep(2.0)

keep = SlowToFinalize()
cli.run_program()
"""


@pytest.mark.multiprocess
def test_sigterm_while_exiting_keeps_the_exit_status():
    """``up`` stops its children at the end of a run; a SIGTERM that reaches a process
    already in the interpreter's shutdown must not turn its status into -15."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_EXIT], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, start_new_session=True)
    try:
        assert proc.stdout.readline() == b"exiting\n"
        os.killpg(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=60) == 3
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


_BUSY_COMMAND = """
import sys, time
import agent.cli.analyze as analyze
import agent.cli.main as cli

def busy(args):                        # a command at work that never handles SIGTERM
    print("working", flush=True)
    while True:
        time.sleep(0.05)

analyze.run = busy
sys.argv = ["socmon", "analyze", "paper-14"]
cli.run_program()
"""


@pytest.mark.multiprocess
def test_sigterm_ends_a_command_that_does_not_handle_it_as_ctrl_c_does():
    """``inject`` or ``reproduce`` stopped by SIGTERM: "socmon: interrupted", status 130,
    as with Ctrl-C, not killed by the signal with nothing said."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _BUSY_COMMAND], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True)
    try:
        assert proc.stdout.readline() == b"working\n"
        os.killpg(proc.pid, signal.SIGTERM)
        assert proc.wait(timeout=60) == 130
        assert proc.stderr.read() == b"socmon: interrupted\n"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


# -- warnings of a run ------------------------------------------------------------------------

def test_log_warnings_are_collected_and_bounded(tmp_path):
    (tmp_path / "world.log").write_text(
        "world: 4 agents ready\n"
        "world: warning: rho(A) = 1.0857 > 1: float64 loses an O(1) error from step 427\n")
    (tmp_path / "monitor-2.log").write_text("monitor 2: no warning: here\n")
    # a monitor's warning names its log: which monitor, which life (it was not collected)
    (tmp_path / "monitor-1.restart-1.log").write_text(
        "monitor 1: warning: cannot write events.jsonl: disk full\n")
    assert log_warnings(tmp_path) == [
        "monitor-1.restart-1: cannot write events.jsonl: disk full",
        "world: rho(A) = 1.0857 > 1: float64 loses an O(1) error from step 427"]
    (tmp_path / "monitor-1.restart-1.log").unlink()
    (tmp_path / "agent-1.log").write_text(
        "".join(f"agent-1: warning: late {i}\n" for i in range(MAX_LOG_WARNINGS + 3)))
    found = log_warnings(tmp_path)
    assert found[:2] == ["agent-1: late 0", "agent-1: late 1"]
    assert len(found) == MAX_LOG_WARNINGS + 1
    assert found[-1] == f"4 more warnings in {tmp_path}"
    assert log_warnings(tmp_path / "absent") == []


def test_period_not_sustained_counts_each_missed_estimate_once():
    """An estimate that missed its step is a drop, and a late one too when it comes after:
    the share is of the drops (which hold the late ones), never above 100 %."""
    from agent.run.summary import period_warning

    # at 0.01 ms steps: nearly every input held, most of them then arriving late
    last = {1: {"inputs": {"fresh": 40, "held": 1560, "lost": 0, "none": 0},
                "drops": 1560, "late": 20},
            2: {"inputs": {"fresh": 9, "held": 1550, "lost": 0, "none": 0},
                "drops": 1550, "late": 46},
            3: {}}                                  # an agent never heard from
    assert period_warning(last, faulty=False) == (
        "period not sustained: 3110 of 3159 neighbour estimates (98.4 %) were late or "
        "dropped (the machine is too loaded for this step period, or links are impaired)")
    assert period_warning(last, faulty=True).startswith(
        "period not sustained: 66 of 3159 neighbour estimates (2.1 %) were late (")
    quiet = {1: {"inputs": {"fresh": 1000}, "drops": 10, "late": 10}}
    assert period_warning(quiet, faulty=False) is None


def test_a_step_period_no_agent_can_keep_is_warned_of_at_the_start():
    from agent.run.setup import step_period_warning

    assert step_period_warning(20.0) is None and step_period_warning(1.0) is None
    assert step_period_warning(0.01) == (
        "--step-ms 0.01: below 1 ms, less than an agent's own CPU time a step in a live run "
        "(0.7-1.1 ms measured, docs/runtime.md): the period will not be sustained, and most "
        "neighbour estimates will be late or dropped")


@pytest.mark.parametrize("fault, message", [
    ("drop:10:1:5:2", "drop VALUE is a probability in [0, 1]"),
    ("delay:10:1:5:2.5", "delay VALUE is a whole number of steps"),
    ("kill:10", "kill needs an agent"),
    ("lie:10:1", "lie needs VALUE > 0"),
    ("bias:10:1:0:0", "bias needs VALUE > 0"),
    ("delay:10:1:5", "delay needs VALUE > 0"),
    ("drop:10:1:5:0", "drop needs VALUE > 0"),
])
def test_up_fault_values_are_checked_before_anything_starts(tmp_path, capsys, fault, message):
    """A fault value the impairment could not carry is a usage error, not a crash mid-run."""
    assert main(["up", "paper-14-live", "--out", str(tmp_path / "run"), "--fault", fault]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "run" / "run.json").exists()


def test_up_says_that_a_standby_lies_only_once_it_holds_a_role(tmp_path, capsys, live_gains):
    """``--fault lie`` aimed at standby 4 of paper-14-live is accepted with a note naming it
    (a lie of an agent with a role at the start, none)."""
    from agent.cli.main import build_parser
    from agent.run.setup import run_config

    args = build_parser().parse_args(["up", "paper-14-live", "--gains", str(live_gains),
                                      "--out", str(tmp_path / "run"), "--fault",
                                      "lie:150:4:0:3", "--fault", "bias:150:2:0:3"])
    config = run_config(args, lambda text: None)
    assert [(f.kind, f.agent) for f in config.faults] == [("bias", 2), ("lie", 4)]
    assert capsys.readouterr().err == (
        "up: note: agent 4 is a standby (no role at the start): it lies only once it holds "
        "a role, from the later of step 150 and the first step it computes in one (never, "
        "if it takes none)\n")


@pytest.mark.parametrize("flags, message", [
    (["--kill", "100:1"], "--kill: step 100 is after the run's last step (50, --steps)"),
    (["--stop", "51:2:1"], "--stop: step 51 is after the run's last step (50"),
    (["--kill-monitor", "60"], "--kill-monitor: step 60 is after"),
    (["--fault", "partition:70:1:2"], "--fault: step 70 is after"),
])
def test_up_faults_after_the_last_step_are_refused(tmp_path, capsys, flags, message):
    """A fault scheduled after the run ends would never happen: said, not recorded."""
    assert main(["up", "paper-14-live", "--steps", "50", "--out", str(tmp_path / "run"),
                 *flags]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "run" / "run.json").exists()


@pytest.mark.parametrize("flags, message", [
    (["--fault", "kill:50:1", "--kill", "50:1"],
     "--fault: agent 1 is killed twice (--kill 50:1 and --fault kill:50:1)"),
    (["--fault", "kill:50:1", "--fault", "kill:60:1"], "--fault: agent 1 is killed twice"),
    (["--kill", "50:1", "--kill", "60:1,2"], "--kill: agent 1 is killed twice"),
    (["--stop", "50:1:0"], "--stop: stop needs SECONDS > 0 (how long the agent is stopped)"),
    (["--fault", "stop:50:1"], "--fault: stop needs SECONDS > 0 (how long the agent is stopped)"),
    (["--stop", "50:1:3600"], "--stop: stop needs SECONDS below 3600"),
    (["--fault", "stop:50:1:3600"], "--fault: stop needs SECONDS below 3600"),
    (["--fault", "partition:50:1"], "--fault: partition needs SECONDS > 0"),
    (["--fault", "sensor:50:1:0"], "--fault: sensor needs SECONDS > 0"),
    (["--fault", "hang:50:1:5"], "--fault: hang acts at its step and takes no SECONDS"),
    (["--fault", "kill:50:1:0:3"], "--fault: kill takes no VALUE"),
])
def test_up_holds_every_fault_to_the_same_checks_whatever_its_flag(tmp_path, capsys, flags,
                                                                    message):
    """``--fault KIND`` and the dedicated flags (--kill, --stop, --kill-monitor) meet one
    set of checks: an agent killed twice, a fault that lasts 0 s, a SECONDS or a VALUE
    that would be ignored are refused from either."""
    assert main(["up", "paper-14-live", "--steps", "100", "--out", str(tmp_path / "run"),
                 *flags]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert not (tmp_path / "run" / "run.json").exists()


def test_up_reads_a_fault_alike_from_its_own_flag_and_from_fault():
    from agent.cli.main import build_parser
    from agent.run.local import Fault
    from agent.run.setup import parse_faults
    from design.scenario import load_scenario

    live = load_scenario("paper-14-live")
    parse = build_parser().parse_args
    dedicated = parse(["up", "paper-14-live", "--kill", "50:1", "--stop", "60:2:1.5",
                       "--kill-monitor", "70"])
    general = parse(["up", "paper-14-live", "--fault", "monitor:70", "--fault",
                     "stop:60:2:1.5", "--kill", "50:1"])
    expected = [Fault(50, "crash", 1), Fault(60, "stop", 2, 1.5), Fault(70, "monitor")]
    assert parse_faults(dedicated, live) == parse_faults(general, live) == expected


def test_up_refuses_monitors_without_a_monitor(tmp_path, capsys):
    assert main(["up", "paper-14-live", "--no-monitor", "--monitors", "3",
                 "--out", str(tmp_path / "run")]) == 2
    assert "--monitors: no monitor runs with --no-monitor" in _one_line(capsys.readouterr().err)


@pytest.mark.parametrize("flags", [["--kill-monitor", "50"], ["--fault", "monitor:50"],
                                   ["--fault", "monitorstop:50::2"],
                                   ["--fault", "monitorsgone:50"]])
def test_up_refuses_a_monitor_fault_without_a_monitor(tmp_path, capsys, flags):
    """A fault of the monitor in a run with none would be said and recorded, never done."""
    assert main(["up", "paper-14-live", "--no-monitor", "--steps", "100",
                 "--out", str(tmp_path / "run"), *flags]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"socmon: {flags[0]}: no monitor runs with --no-monitor (give one "
                          f"or the other), got {flags[1]!r}"), err
    assert not (tmp_path / "run" / "run.json").exists()


def test_monitor_faults_are_the_process_faults_on_a_monitor():
    from agent.run.fault_kinds import MONITOR_FAULTS, PROCESS_FAULTS

    assert set(MONITOR_FAULTS) == {k for k in PROCESS_FAULTS if k.startswith("monitor")}


#: one spec of every kind a run injects, as up takes it
ONE_OF_EACH = {"crash": ["--kill", "50:1"], "kill": ["--fault", "kill:50:1"],
               "stop": ["--stop", "50:1:2"], "hang": ["--fault", "hang:50:1"],
               "sensor": ["--fault", "sensor:50:1:2"], "monitor": ["--kill-monitor", "50"],
               "partition": ["--fault", "partition:50:1:2"],
               "delay": ["--fault", "delay:50:1:2:1"], "drop": ["--fault", "drop:50:1:2:0.5"],
               "linkdown": ["--netns", "--fault", "linkdown:50:1:2"],
               "worldstop": ["--fault", "worldstop:50::2"],
               "monitorstop": ["--fault", "monitorstop:50::2"],
               "monitorsgone": ["--fault", "monitorsgone:50"],
               "lie": ["--fault", "lie:50:1:0:3"], "bias": ["--fault", "bias:50:1:0:3"],
               "drift": ["--fault", "drift:50:1:0:1"], "noise": ["--fault", "noise:50:1:0:2"]}


def test_one_of_each_covers_every_kind_and_replayed_ones_are_the_simulators():
    from agent.run.fault_kinds import FAULT_KINDS, REPLAYED_FAULTS, SCRIPTED_FAULTS
    from design.simulate import FAULT_KINDS as SIMULATED

    assert set(ONE_OF_EACH) == set(FAULT_KINDS)
    assert set(REPLAYED_FAULTS) == {"crash", *SIMULATED} == set(SCRIPTED_FAULTS)


@pytest.mark.parametrize("kind", sorted(ONE_OF_EACH))
def test_check_simulator_refuses_at_the_start_what_the_simulator_does_not_replay(kind):
    """Each kind against --check-simulator: the replayed ones (a scripted crash, a lie, a
    sensor fault) accepted, every other refused before the run, naming its flag."""
    from agent.cli.main import build_parser
    from agent.run.fault_kinds import REPLAYED_FAULTS
    from agent.run.inputs import InputError
    from agent.run.setup import parse_faults
    from design.scenario import load_scenario

    flags = ONE_OF_EACH[kind]
    args = build_parser().parse_args(["up", "paper-14-live", "--steps", "100",
                                      "--check-simulator", *flags])
    live = load_scenario("paper-14-live")
    if kind in REPLAYED_FAULTS:
        assert [f.kind for f in parse_faults(args, live)] == [kind]
        return
    with pytest.raises(InputError) as info:
        parse_faults(args, live)
    given = " ".join(flags[-2:]) if flags[-2].startswith("--") else flags[-1]
    assert str(info.value).startswith(f"--check-simulator: the simulator does not replay "
                                      f"{given} ("), str(info.value)
    assert str(info.value).endswith("only (give one or the other)")


def test_check_simulator_with_the_monitor_killed_is_refused_before_anything_starts(
        tmp_path, capsys):
    assert main(["up", "communities-16", "--check-simulator", "--kill-monitor", "50",
                 "--steps", "100", "--out", str(tmp_path / "run")]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith("socmon: --check-simulator: the simulator does not replay "
                          "--kill-monitor 50 (monitor killed (SIGKILL), started again)")
    assert not (tmp_path / "run").exists()


def test_a_run_that_cannot_be_replayed_is_not_compared_rather_than_differing_by_inf():
    """What only the run can tell (a reassignment without a scripted crash): said as not
    compared, not as a difference of inf; a real difference still says by how much."""
    from agent.run.setup import simulator_problem

    why = "a reassignment without a scripted crash cannot be replayed"
    assert simulator_problem(float("inf"), why) == (
        f"--check-simulator: the run was not compared with the simulator's replay: {why}")
    assert simulator_problem(1e-15, "estimates (100 compared)") is None
    assert simulator_problem(0.25, "estimates (100 compared; the first above 1e-09: agent 1 "
                                   "at step 105)").startswith(
        "--check-simulator: the run differs from the simulator's replay by 0.25 (relative")


@pytest.mark.parametrize("command", ["watch", "monitor"])
def test_attach_to_a_run_of_another_scenario_names_both_scenarios(tmp_path, capsys, command):
    """SCENARIO given beside --attach of a run of another one: said as such, not as the
    run's gains not fitting a scenario the user did not give them for."""
    from agent.run.folder import write_run_json

    write_run_json(tmp_path, run="demo", connect="tcp/127.0.0.1:9", processes={},
                   scenario="communities-16", scenario_arg="communities-16",
                   gains=tmp_path / "gains.npz")
    assert main([command, "communities-32", "--attach", str(tmp_path)]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err == (f"socmon: SCENARIO: the run in {str(tmp_path)!r} (--attach) is of scenario "
                   "communities-16, not communities-32 (leave SCENARIO out to take the "
                   "run's)\n")


def test_a_difference_after_an_injection_says_the_simulator_does_not_replay_it():
    """Impairments set during the run (by ``socmon inject``: an agent's status shows its
    links changed) are said with the difference; the run's own delays are not an
    injection."""
    from agent.run.setup import simulator_problem
    from agent.run.summary import links_impaired
    from design.scenario import load_scenario

    live = load_scenario("paper-14-live")
    how = "estimates (2501 compared; the first above 1e-09: agent 2 at step 105)"
    events = [{"process": "agent-2", "links": {"3": {"drop": 0.5}}, "step": 100},
              {"process": "agent-2", "links": {}, "step": 160},
              {"process": "monitor", "signal": "SIGKILL", "step": 50}]
    impaired = links_impaired(events, live, np.zeros((3, 3), dtype=int))
    assert impaired == [(100, 2)]
    assert simulator_problem(0.253, how, impaired) == (
        f"--check-simulator: the run differs from the simulator's replay by 0.253 (relative; "
        f"at most 1e-09 allowed): {how}; link impairments were set during the run (the "
        "links into agent 2 at step 100: socmon inject, or anyone with the operator key), "
        "and the simulator does not replay them")
    assert "link impairments" not in simulator_problem(0.253, how, [])
    # a delayed run's own links (its delays, in force from the start) are no injection
    delays = np.ones((3, 3), dtype=int)
    own = {"process": "agent-1", "links": {str(b): {"delay_steps": 1} for b in (2, 3, 4)},
           "step": -1}
    assert links_impaired([own], live, delays) == []


def test_version_is_printed(capsys):
    from importlib.metadata import version

    assert main(["--version"]) == 0
    assert capsys.readouterr().out == f"socmon {version('socmon')}\n"


def test_plan_without_new_links_says_and_exits_as_planned(capsys):
    """paper-14 losing agents 1 and 2 needs a new link: without it, not recoverable."""
    assert main(["plan", "paper-14", "--fail", "1,2", "--no-new-links"]) == 1
    out = capsys.readouterr().out
    assert "recoverable without new links: no (yes if plan may add links" in out
    assert "\nrecoverable: yes" not in out
    assert main(["plan", "paper-14", "--fail", "1,2"]) == 0
    assert "recoverable: yes" in capsys.readouterr().out


@pytest.mark.parametrize("plot, message", [
    ("mse.txt", "--plot: cannot write a '.txt' figure; use one of .png"),
    ("nowhere/mse.png", "--plot: folder 'nowhere' does not exist"),
])
def test_simulate_plot_path_is_checked_before_simulating(paper14_gains, tmp_path,
                                                           monkeypatch, capsys, plot, message):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "paper-14", "--gains", paper14_gains, "--steps", "5",
                 "--trials", "1", "--plot", plot]) == 2
    assert message in _one_line(capsys.readouterr().err)


def test_simulate_plot_without_suffix_writes_and_names_a_png(paper14_gains, tmp_path, capsys):
    assert main(["simulate", "paper-14", "--gains", paper14_gains, "--steps", "5",
                 "--trials", "1", "--plot", str(tmp_path / "mse")]) == 0
    assert f"figure: {tmp_path / 'mse.png'}" in capsys.readouterr().out
    assert (tmp_path / "mse.png").is_file()


@pytest.mark.parametrize("argv", [["up", "paper-14-live", "--steps", "-5"],
                                  ["chaos", "paper-14-live", "--duration", "ten"],
                                  ["keys", "init"]])
def test_a_flag_argparse_rejects_is_one_line_naming_it(capsys, argv):
    """Bad input exits 2 with a one-line message (the README's promise), not the whole
    usage block before it."""
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"socmon {argv[0]}")
    assert ("--steps" in err[0] or "--duration" in err[0] or "DIR" in err[0])
    assert err[0].endswith(f"--help`)")


@pytest.mark.parametrize("argv", [["up", "communities-16", "--stepz", "10"],
                                  ["analyze", "communities-16", "--bogus"]])
def test_an_unknown_flag_of_a_command_is_the_commands_error(capsys, argv):
    """A flag the command does not know is said by the command's parser, one line, as its
    other errors are; not the top level's usage."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (f"socmon {argv[0]}: error: unrecognized arguments: {' '.join(argv[2:])} "
                   f"(see `socmon {argv[0]} --help`)\n")


def test_inject_names_a_value_out_of_range_in_its_own_words(capsys):
    """The impairment's range check, said as the command's words (not the codec's)."""
    assert main(["inject", "drop", "1", "2", "1.5", "--connect", "tcp/127.0.0.1:9"]) == 2
    assert capsys.readouterr().err.strip() == "socmon: drop: 1.5 outside [0.0, 1.0]"
    assert main(["inject", "delay", "1", "2", "--ms", "1e9", "--connect",
                 "tcp/127.0.0.1:9"]) == 2
    assert "delay: delay_ms 1000000000.0 outside" in capsys.readouterr().err


def test_inject_that_reaches_no_run_says_so_not_that_the_agent_is_dead(capsys):
    """No process listens at the endpoint: inject sees no agent at all, and says the run
    was not reached (not "agent 1 not alive"), and that it published nothing."""
    import socket

    with socket.socket() as s:              # a free port: nothing of any run listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["inject", "delay", "1", "2", "--steps", "3", "--connect",
                 f"tcp/127.0.0.1:{port}", "--timeout", "0.5", "--run", "nobody"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("socmon: no agent of run 'nobody' seen within 0.5 s through "
                          f"tcp/127.0.0.1:{port}"), err
    assert err.endswith("(nothing was published)") and "not alive" not in err


def test_a_session_that_cannot_open_is_one_line_and_exit_1(capsys):
    """A secured process that reached none of its connect endpoints in time (zenoh's
    error, with the endpoints): one line, status 1, no traceback."""
    from types import SimpleNamespace

    from broker_free_net.peer import SessionError

    from agent.cli._common import run_command

    # the endpoints of a secured process's NetConfig (its keys left out here)
    net = SimpleNamespace(connect=("tls/127.0.0.1:37599",), listen=("tls/127.0.0.1:0",))

    def body():
        raise SessionError(net, "Unable to connect to any of [Single(tls/127.0.0.1:37599)]. "
                                "Timeout!")

    assert run_command(body) == 1
    err = capsys.readouterr().err.strip()
    assert err == ("socmon: cannot open the zenoh session (listen on tls/127.0.0.1:0; "
                   "connect to tls/127.0.0.1:37599): Unable to connect to any of "
                   "[Single(tls/127.0.0.1:37599)]. Timeout!")
    with pytest.raises(ValueError):             # anything else is not swallowed
        run_command(lambda: int("x"))
