"""Shared fixtures: the shared data folder beside the project, built-in scenarios."""

from pathlib import Path

import pytest
from threadpoolctl import threadpool_limits

# Tests run many small dense decompositions; on a loaded 2-core machine BLAS threads only
# contend (see agent/cli.py). Limit the pool for the whole session.
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
def sampson_edges():
    if not SAMPSON_EDGES.is_file():
        pytest.skip(f"shared data not found at {SAMPSON_EDGES}")
    return SAMPSON_EDGES
