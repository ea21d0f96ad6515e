"""The words of a run's ``mse.png``: a title that fits whatever the number of agents."""

import pytest

from agent.run.summary import TITLE_CHARS, plot_title


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
