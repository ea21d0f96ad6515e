"""The runtime's periods and timeouts: one object, every relation refused with its name."""

import math

import pytest

from agent.cli._common import CommandError, timing_arg
from agent.monitor.core import MonitorConfig
from agent.protocol.timing import DEFAULT, Timing, TimingError


def test_the_defaults_are_consistent_and_are_what_the_monitor_uses():
    assert DEFAULT.problems(step_s=0.02, lead_steps=MonitorConfig.lead_steps) == []
    cfg = MonitorConfig()
    assert cfg.hang_timeout_s == DEFAULT.hang_timeout_s
    assert cfg.pause_guard_s == DEFAULT.pause_guard_s
    assert cfg.world_gone_s == DEFAULT.monitor_world_gone_s
    assert MonitorConfig.from_timing(DEFAULT) == cfg


# one case per relation: the change that breaks it and the field the refusal names
BROKEN = [
    ({"status_s": 0.6}, "hang_timeout_s", "2 x status_s"),
    ({"status_s": 0.05}, "prestart_status_s", "status_s"),
    ({"pause_guard_s": 1.0}, "pause_guard_s", "hang_timeout_s"),
    ({"resend_s": 3.0}, "resend_s", "confirm_timeout_s"),
    ({"rejoin_s": 1.0}, "rejoin_s", "hang_timeout_s"),
    ({"agent_world_gone_s": 5.0}, "agent_world_gone_s", "world_grace_s"),
    ({"monitor_world_gone_s": 10.0}, "monitor_world_gone_s", "agent_world_gone_s"),
    ({"crash_flush_s": 1.0}, "crash_flush_s", "hang_timeout_s"),
    ({"step_ahead_s": 0.3}, "step_ahead_s", "2 x status_s"),
    ({"hang_timeout_max_s": 0.5}, "hang_timeout_max_s", "hang_timeout_s"),
    ({"world_silent_s": 8.0}, "world_silent_s", "agent_world_gone_s"),
    ({"monitor_world_silent_s": 50.0}, "monitor_world_silent_s", "world_silent_s"),
]


@pytest.mark.parametrize("change,field,relation", BROKEN, ids=[b[1] for b in BROKEN])
def test_each_broken_relation_is_refused_naming_it(change, field, relation):
    timing = DEFAULT.replace(**change)
    problems = timing.problems()
    assert len(problems) == 1, problems
    assert problems[0].startswith(f"{field}: ") and relation in problems[0]
    with pytest.raises(TimingError, match=field):
        timing.validate()


def test_a_step_period_must_show_progress_within_the_confirm_timeout():
    """An agent confirms an assignment by the status showing it pending, whatever the head
    start: 10 lead steps of 0.3 s (3 s, the whole confirm timeout) are fine (they were
    refused). What the timeout bounds is a healthy agent's time without a new step."""
    assert DEFAULT.problems(step_s=0.02, lead_steps=10) == []
    assert DEFAULT.problems(step_s=0.3, lead_steps=10) == []
    assert DEFAULT.problems(step_s=2.7, lead_steps=10) == []
    problems = DEFAULT.problems(step_s=2.8, lead_steps=10)
    assert len(problems) == 1 and problems[0].startswith("step_s: ")
    assert "--step-ms" in problems[0] and "the longest period is 2800 ms" in problems[0]


@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, True])
def test_values_that_are_not_positive_finite_numbers_are_refused(value):
    problems = Timing(hang_timeout_s=value).problems()
    assert problems == [f"hang_timeout_s: must be a finite number > 0, got {value!r}"]


def test_a_flag_that_breaks_a_relation_is_named_by_its_flag():
    with pytest.raises(CommandError, match=r"^--hang-timeout: 0.3 s must exceed pause_guard_s"):
        timing_arg(hang_timeout_s=0.3)
    assert timing_arg(hang_timeout_s=2.0).hang_timeout_s == 2.0
    assert timing_arg(hang_timeout_s=None) == DEFAULT


@pytest.mark.parametrize("fields, message", [
    # below 2 x status_s, pause_guard_s and crash_flush_s: the highest of the three alone
    ({"hang_timeout_s": 0.1}, "--hang-timeout: 0.1 s must exceed pause_guard_s = 0.5 s (a "
     "monitor paused longer than a hang would convict on stale clocks)"),
    ({"hang_timeout_s": 0.45}, "--hang-timeout: 0.45 s must exceed pause_guard_s = 0.5 s ("),
    ({"hang_timeout_s": 100.0, "hang_timeout_max_s": 5.0},
     "--hang-timeout: 100 s must be below rejoin_s = 5 s ("),
    ({"hang_timeout_s": 1.0, "hang_timeout_max_s": 0.5},
     "--hang-timeout-max: 0.5 s must be at least --hang-timeout = 1 s (the adaptive timeout"),
    ({"start_timeout_s": 1.0}, "--start-timeout: 1 s must exceed monitor_prepare_s = 20 s ("),
])
def test_a_flag_is_refused_with_the_one_bound_it_can_meet(fields, message):
    """The flag and the tightest bound it breaks, first and alone: not every internal
    setting it is below, nor a relation of the runtime's own settings named first."""
    with pytest.raises(CommandError) as info:
        timing_arg(**fields)
    text = str(info.value)
    assert text.startswith(message) and ";" not in text, text


def test_bounds_are_the_relations_seen_from_one_field():
    bounds = {(op, bound, other) for op, bound, other, _, _ in DEFAULT.bounds("hang_timeout_s")}
    assert bounds == {(">", 0.4, "status_s"), ("<=", 5.0, "hang_timeout_max_s"),
                      (">", 0.5, "pause_guard_s"), ("<", 5.0, "rejoin_s"),
                      (">", 0.3, "crash_flush_s")}


def test_up_refuses_a_hang_timeout_below_the_pause_guard(capsys):
    from agent.cli.main import main

    assert main(["up", "paper-14-live", "--steps", "5", "--hang-timeout", "0.3"]) == 2
    err = capsys.readouterr().err
    assert err == ("socmon: --hang-timeout: 0.3 s must exceed pause_guard_s = 0.5 s (a "
                   "monitor paused longer than a hang would convict on stale clocks)\n")


def test_monitor_refuses_a_hang_timeout_below_the_pause_guard(capsys, live_gains):
    from agent.cli.main import main

    assert main(["monitor", "paper-14-live", "--run", "t", "--gains", str(live_gains),
                 "--hang-timeout", "0.3"]) == 2
    err = capsys.readouterr().err
    assert "--hang-timeout: 0.3 s must exceed pause_guard_s = 0.5 s" in err


def test_the_monitor_reads_its_lease_from_its_transport_flags(live_gains):
    """``--lease-ms`` reaches the detector (a recent word is 0.8 of it), not only zenoh."""
    import argparse

    from agent.cli import _common
    from agent.cli.monitor import add_arguments
    from agent.run.monitor_options import monitor_options

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    base = ["paper-14-live", "--run", "t", "--gains", str(live_gains)]
    for extra, lease_s in (([], 1.0), (["--lease-ms", "400"], 0.4)):
        options = monitor_options(parser.parse_args(base + extra), None,
                                  net_config_arg=_common.net_config_arg,
                                  load_signer=_common.load_signer)
        assert options.config.lease_s == lease_s
