"""The words of a run's ``mse.png``: a title that fits whatever the number of agents, and
labels that stay readable when events share a step."""

import pytest

from agent.run.summary import TITLE_CHARS, event_labels, plot_title


def _summary(scenario, rosters):
    return {"scenario": scenario, "seed": 0,
            "rosters": [{"activate_at": at, "ids": list(ids), "epoch": e}
                        for e, (at, ids) in enumerate(rosters)]}


@pytest.mark.parametrize("N", [16, 64])
def test_the_title_of_a_large_run_fits_its_width_and_starts_with_the_scenario(N):
    """16 agents, agent 5 failed and new gains later: every id of the first and last
    roster made 170 characters, and the title's start fell off the figure."""
    everyone = range(1, N + 1)
    left = [a for a in everyone if a != 5]
    title = plot_title(_summary(f"communities-{N}", [(0, everyone), (161, left), (184, left)]))
    assert title == (f"communities-{N}, seed 0: {N} agents; from step 161: all but 5 "
                     "(1 reassignment)")
    assert len(title) - len(f"communities-{N}") <= TITLE_CHARS


def test_a_title_of_scattered_rosters_falls_back_to_counts():
    first = range(1, 65)
    last = [a for a in first if a % 3] + [65, 67, 69]         # 21 lost, 3 standbys in
    title = plot_title(_summary("big", [(0, first), (150, last)]))
    assert title.startswith("big, seed 0: 64 agents; from step 150: ")
    assert len(title) - len("big") <= TITLE_CHARS


def test_new_gains_for_the_same_roles_are_no_reassignment_in_the_title():
    title = plot_title(_summary("p", [(0, (1, 2, 3)), (120, (1, 2, 3))]))
    assert title == "p, seed 0: 3 agents"


def test_two_failures_at_one_step_make_one_label_of_each_kind():
    """``--kill 200:3,11``: "crash 3" and "crash 11" were printed on one another."""
    faults = [{"step": 200, "kind": "crash", "agent": 3, "seconds": 0.0, "value": 0.0},
              {"step": 200, "kind": "crash", "agent": 11, "seconds": 0.0, "value": 0.0}]
    failures = [{"agent": 3, "cause": "crash", "detected_step": 201, "activate_at": 212,
                 "replacement": {"agent": 2}},
                {"agent": 11, "cause": "crash", "detected_step": 202, "activate_at": 212,
                 "replacement": {"agent": 1}}]
    labels = event_labels({"faults": faults, "failures": failures}, near=6)
    assert labels == {"faults": [(200, 200, "crash 3, 11")],
                      "detected": [(201, 202, "agents 3, 11: crash")],
                      "reassigned": [(212, 212, "agent 2 for 3, agent 1 for 11")]}


def test_events_apart_keep_labels_of_their_own_and_causes_are_named_each():
    failures = [{"agent": 3, "cause": "crash", "detected_step": 100},
                {"agent": 4, "cause": "hang", "detected_step": 100},
                {"agent": 7, "cause": "crash", "detected_step": 180},
                {"agent": 9, "detected": False, "died_step": 250}]
    labels = event_labels({"failures": failures}, near=6)
    assert labels["detected"] == [(100, 100, "agent 3: crash; agent 4: hang"),
                                  (180, 180, "agent 7: crash")]
    assert labels["reassigned"] == [] and labels["faults"] == []
