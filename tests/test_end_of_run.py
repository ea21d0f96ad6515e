"""What ``up`` says on the terminal around the end of a run."""

from agent.protocol.timing import DEFAULT as TIMING
from agent.run.local import EndOfRun, end_wait_words


def test_the_last_progress_line_is_said_once_then_once_what_up_waits_for():
    """An agent stopped at the last step: up waited for its estimate and said the same
    "step 100/100 ..." line every second (6 to 10 times), nothing of why."""
    end, said = EndOfRun(100), []
    for k in (90, 99, 100, 100, 100, 100, 100, 100, 100, 100, 100, 100):
        said += end.lines(k, lambda: f"step {k}/100", lambda: "the estimate of agent 2")
    assert said == ["step 90/100", "step 99/100", "step 100/100",
                    "waiting for the estimate of agent 2"]


def test_what_up_waits_for_names_the_agents_and_the_longest_wait():
    both = end_wait_words(600, True, [3, 11], True)
    assert both.startswith("the estimates of step 600 of agents 3, 11 and the world to end")
    assert both.endswith(f"at most {TIMING.end_timeout_s + TIMING.up_end_s:g} s, then up "
                         "stops the processes")
    assert end_wait_words(600, False, [], False) == (
        f"the world's step 600; at most {TIMING.up_end_s:g} s, then up stops the processes")
