"""Generated scenarios (design.generate) and the built-in scale scenarios made from them."""

import json

import numpy as np
import pytest

from agent.cli.main import main
from design.analysis import structural_analysis
from design.generate import communities_scenario
from design.observability import distributed_detectability, pair_observability
from design.scenario import load_scenario, scenario_from_dict


def test_small_instance_by_hand():
    # 2 communities of 2 and a public of 2: community c listens to public c % 2
    s = scenario_from_dict(communities_scenario(2, public=2, seed=3, spectral_radius=0.9))
    assert s.labels == ("c1a", "c1b", "c2a", "c2b", "p1", "p2")
    nz = {(s.labels[i], s.labels[j]) for i, j in zip(*np.nonzero(s.A))}
    loops = {(x, x) for x in s.labels}
    assert nz == loops | {("c1a", "c1b"), ("c1b", "c1a"), ("c2a", "c2b"), ("c2b", "c2a"),
                          ("p1", "p2"), ("p2", "p1"), ("c1a", "p1"), ("c2a", "p2")}
    assert s.rho_A == pytest.approx(0.9)
    assert [s.agent_labels(i) for i in range(s.N)] == [["c1a"], ["c2a"]]
    np.testing.assert_allclose(s.W, [[0.6, 0.4], [0.4, 0.6]])


def test_every_community_is_a_measured_parent_scc():
    s = scenario_from_dict(communities_scenario(5, size=3, public=2, seed=1))
    st = structural_analysis(s.A, measured=[v for m in s.measure for v in m]).structure
    parents = sorted(sorted(s.labels[v] for v in st.components[c]) for c in st.parents)
    assert parents == sorted([f"c{c}{m}" for m in "abc"] for c in range(1, 6))
    assert pair_observability(s.A, s.H_all).observable
    assert distributed_detectability(s.A, s.W, s.measure).observable


@pytest.mark.parametrize("N", [16, 32])
def test_builtin_scale_scenarios_are_the_generator_output(N):
    built = load_scenario(f"communities-{N}")
    fresh = scenario_from_dict(communities_scenario(N, seed=N))
    assert built.name == f"communities-{N}" and built.N == N and built.n == 2 * N + 4
    assert built.labels == fresh.labels
    assert [list(m) for m in built.measure] == [list(m) for m in fresh.measure]
    np.testing.assert_array_equal(built.A, fresh.A)
    np.testing.assert_array_equal(built.W, fresh.W)
    assert built.step_ms == 10


@pytest.mark.slow
def test_communities_16_is_observable_and_gets_a_stable_gain(tmp_path, capsys):
    s = load_scenario("communities-16")
    d = distributed_detectability(s.A, s.W, s.measure)
    assert (d.rank, d.order) == (576, 576)
    status = main(["design", "communities-16", "--target", "0.97", "--out",
                   str(tmp_path / "g.npz"), "--json"])
    out = json.loads(capsys.readouterr().out)
    assert status == 0 and out["stable"] and out["rho_exact"] < 0.97


@pytest.mark.parametrize("kwargs, field", [
    ({"N": 0}, "N"), ({"N": 3, "size": 0}, "size"), ({"N": 3, "public": True}, "public"),
    ({"N": 3, "standby": 4}, "standby"), ({"N": 3, "size": 1, "standby": 1}, "standby"),
])
def test_bad_arguments_name_the_argument(kwargs, field):
    with pytest.raises(ValueError, match=f"^{field}:"):
        communities_scenario(**kwargs)
