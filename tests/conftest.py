"""Shared fixtures: the shared data folder beside the project, built-in scenarios."""

from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

# Tests run many small dense decompositions; on a loaded 2-core machine BLAS threads only
# contend (see agent/cli/main.py). Limit the pool for the whole session.
_BLAS_LIMIT = threadpool_limits(limits=1, user_api="blas")

ROOT = Path(__file__).resolve().parents[1]
# the shared folder sits beside the project (../shared); from a worktree two levels
# down (/work/wt/<branch>) it is ../../shared: take the nearest ancestor that has it
SHARED = next(
    (p / "shared" for p in ROOT.parents if (p / "shared" / "data").is_dir()),
    ROOT.parent / "shared",
)
SAMPSON_EDGES = SHARED / "data" / "sampson" / "sampson_samplike_edges.csv"


@pytest.fixture(scope="session")
def paper14():
    from design.scenario import load_scenario

    return load_scenario("paper-14")


@pytest.fixture(scope="session")
def paper14_design(paper14):
    """``design_gains(paper14, starts=1, max_iter=40)``: the default design of paper-14 at
    its own delays (none), computed once for the modules that need a stabilising gain of
    paper-14 (about 2 s a design). Its arrays are read-only: a test that wrote into them
    would fail instead of changing the gain another test reads."""
    from design.gain_design import design_gains

    res = design_gains(paper14, starts=1, max_iter=40)
    for a in (*res.G, res.delays):
        a.setflags(write=False)
    return res


@pytest.fixture(scope="session")
def sampson_edges():
    if not SAMPSON_EDGES.is_file():
        pytest.skip(f"shared data not found at {SAMPSON_EDGES}")
    return SAMPSON_EDGES


@pytest.fixture(scope="session")
def live_gains(tmp_path_factory):
    """The gains file of fixed gains for paper-14-live (0.5 on each measured node), stable
    with and without the scenario's link delays."""
    import numpy as np

    from design.closed_loop import closed_loop_for
    from design.gains import save_gains
    from design.scenario import load_scenario, resolve_delays

    s = load_scenario("paper-14-live")
    G = [0.5 * np.eye(s.n)[:, list(m)] for m in s.measure]
    rho = {d: closed_loop_for(s, G, resolve_delays(s, d)).spectral_radius()
           for d in ("none", "scenario")}
    assert max(rho.values()) < 1, rho
    path = tmp_path_factory.mktemp("gains") / "live.npz"
    save_gains(path, G, {"method": "fixed", "rho": rho["scenario"]})
    return path


@pytest.fixture
def children(tmp_path):
    """Child processes started in their own process groups (logs under ``tmp_path``),
    always stopped at teardown."""
    from agent.run.launcher import Children

    ch = Children(tmp_path / "logs")
    try:
        yield ch
    finally:
        ch.stop_all(grace=5.0)
