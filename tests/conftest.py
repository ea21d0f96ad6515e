"""Shared fixtures: the shared data folder beside the project, built-in scenarios."""

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
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
