"""``agent.run.launcher.Children``: every exit is reported once, whoever noticed it first.

Children in their own process groups, waits on conditions with deadlines, always stopped.
"""

import pytest

from agent.run.launcher import Children
from tests.waiting import wait_until

pytestmark = [pytest.mark.multiprocess]


def test_an_exit_found_by_running_is_still_reported_by_the_next_reap(tmp_path):
    """The run loop asks ``running()`` between two ``reap()`` calls; a child that exits in
    between must still be reported (the run records its exit status from that report)."""
    children = Children(tmp_path / "logs")
    try:
        children.start("agent-9", ["no-such-command"])         # argparse: exit status 2
        assert wait_until(lambda: not children.running(), timeout=60.0)
        reported = children.reap()
        assert [(c.name, c.returncode) for c in reported] == [("agent-9", 2)]
        assert children.reap() == []                           # once, not twice
    finally:
        children.stop_all(grace=5.0)
