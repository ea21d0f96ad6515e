"""Scenario loading: every bad-input case named in the message; Sampson; round trip."""

import re
import textwrap
import warnings

import numpy as np
import pytest

from design.errors import ScenarioError
from design.scenario import (
    RankDeficientWarning,
    load_scenario,
    scenario_from_dict,
    scenario_to_toml,
)

GOOD = {
    "name": "t",
    "social": {"A": [[1.0, 0.5], [0.0, 0.9]]},
    "agents": {"measure": [["1"], ["2"]]},
    "network": {"weights": [[0.5, 0.5], [0.5, 0.5]]},
}


def with_changes(**sections):
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in GOOD.items()}
    for sec, change in sections.items():
        for key, value in change.items():
            if value is None:
                data[sec].pop(key, None)
            else:
                data[sec][key] = value
    return data


def write(tmp_path, text, name="s.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_good_minimal_scenario():
    s = scenario_from_dict(GOOD)
    assert (s.n, s.N) == (2, 2)
    np.testing.assert_array_equal(s.delays, np.zeros((2, 2), int))


@pytest.mark.parametrize("changes, message", [
    ({"social": {"A": [[1.0, 0.5, 0.0], [0.0, 0.9, 0.1]]}}, "social.A: must be square, got 2 x 3"),
    ({"social": {"A": [[1.0, 0.5], [0.0]]}}, "social.A: rows have different lengths"),
    ({"social": {"A": [[1.0, float("nan")], [0.0, 0.9]]}},
     "social.A: non-finite entry at row 1, column 2"),
    ({"social": {"A": [[1.0, float("inf")], [0.0, 0.9]]}}, "social.A: non-finite entry"),
    ({"social": {"labels": ["a", "b", "c"]}}, "social.labels: 3 labels for n = 2 nodes"),
    ({"network": {"weights": [[1.0]]}},
     "network.weights: must be 2 x 2 (one row per agent in agents.measure), got 1 x 1"),
    ({"network": {"weights": [[0.5, 0.6], [0.5, 0.5]]}},
     "network.weights: not row-stochastic: rows of agents [1] sum to [1.1]"),
    ({"network": {"weights": [[1.5, -0.5], [0.5, 0.5]]}},
     "network.weights: negative weight at agent 1, neighbour 2"),
    ({"network": {"weights": [[0.0, 1.0], [0.5, 0.5]]}},
     "network.weights: zero self weight w_ii for agents [1]"),
    ({"network": {"weights": [[1.0, 0.0], [0.5, 0.5]]}},
     "agent graph G_W is not strongly connected; its components are [[1], [2]]"),
    ({"network": {"delays": [[0, -1], [2, 0]]}}, "network.delays: negative delay -1 on link 2 -> 1"),
    ({"network": {"delays": [[0, 1.5], [2, 0]]}},
     "network.delays: entries must be integers (steps), got 1.5"),
    ({"network": {"delays": [[0, 1], [2]]}},
     "network.delays: must be a 2 x 2 matrix of integers, got rows of lengths 2, 1"),
    ({"agents": {"measure": [["1"], ["zz"]]}}, "agents.measure[1] (agent 2): unknown node label 'zz'"),
    ({"agents": {"measure": [["1"], []]}}, "agents.measure[1] (agent 2): agent 2 must measure"),
    ({"agents": {"measure": [["1", "1"], ["2"]]}}, "agents.measure[0] (agent 1): agent 1 lists '1' twice"),
    ({"agents": {"standby": -1}}, "agents.standby: must be a non-negative integer"),
    ({"social": {"process_noise": -0.1}}, "social.process_noise: must be a finite non-negative"),
])
def test_bad_input_is_named(changes, message):
    with pytest.raises(ScenarioError, match=re.escape(message)):
        scenario_from_dict(with_changes(**changes))


def test_delay_on_a_link_that_does_not_exist():
    data = {
        "social": {"A": [[1.0, 0.5], [0.0, 0.9]]},
        "agents": {"measure": [["1"], ["2"], ["1"]]},
        "network": {"topology": "cycle", "self_weight": 0.5,
                    "delays": [[0, 1, 0], [0, 0, 1], [2, 0, 3]]},
    }
    with pytest.raises(ScenarioError, match=re.escape("self link of agent 3 must have delay 0")):
        scenario_from_dict(data)
    data["network"]["delays"] = [[0, 1, 4], [0, 0, 1], [2, 0, 0]]
    with pytest.raises(ScenarioError,
                       match=re.escape("delay 4 on link 3 -> 1, which is not a link of W")):
        scenario_from_dict(data)


def test_every_problem_is_reported_at_once():
    bad = with_changes(social={"labels": ["a", "b", "c"]}, network={"weights": [[0.0, 1.0], [0.5, 0.5]]})
    bad["agents"]["colour"] = "red"
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(bad)
    text = str(info.value)
    assert "3 problems" in text or len(info.value.problems) >= 3
    assert "agents.colour: unknown key" in text
    assert "social.labels" in text and "zero self weight" in text


def test_rank_deficient_A_is_a_warning_not_an_error():
    data = with_changes(social={"A": [[1.0, 1.0], [1.0, 1.0]]})
    with pytest.warns(RankDeficientWarning, match=r"social.A: rank 1 < n = 2"):
        s = scenario_from_dict(data)
    assert s.warnings and "Assumption 1" in s.warnings[0]


def test_edges_file_bad_header(tmp_path):
    (tmp_path / "e.csv").write_text("from,to\n1,2\n2,1\n")
    path = write(tmp_path, """
        [social]
        edges = "e.csv"
        [agents]
        measure = [["1"]]
    """)
    with pytest.raises(ScenarioError, match=r"social.edges: .*e.csv: bad header \['from', 'to'\]"):
        load_scenario(path)


def test_edges_header_names_the_listener_first_and_the_old_header_still_reads(tmp_path):
    """Row ``i,j``: i listens to j (``A[i, j] != 0``). The header ``listener,influencer``
    says so; ``source,target`` said the reverse of what its rows mean: still read the same
    way (nobody's file changes meaning), with a warning naming the fix."""
    from design.scenario import DeprecatedEdgesHeader

    def load(header):
        (tmp_path / "e.csv").write_text(f"{header}\n1,2\n2,1\n2,3\n")
        return load_scenario(write(tmp_path, """
            [social]
            edges = "e.csv"
            [agents]
            measure = [["1"]]
        """))

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        new = load("listener,influencer")
    assert new.A[1, 2] != 0 and new.A[2, 1] == 0          # 2 listens to 3
    with pytest.warns(DeprecatedEdgesHeader,
                      match=r"header source,target is deprecated: .* rename the header "
                            r"listener,influencer \(or i,j\)"):
        old = load("source,target")
    assert np.array_equal(old.A != 0, new.A != 0)


def test_edges_file_unknown_ids(tmp_path):
    (tmp_path / "e.csv").write_text("listener,influencer\na,b\nb,c\nc,a\n")
    path = write(tmp_path, """
        [social]
        edges = "e.csv"
        labels = ["a", "b"]
        [agents]
        measure = [["a"]]
    """)
    with pytest.raises(ScenarioError, match=re.escape("ids not among social.labels: ['c']")):
        load_scenario(path)


def test_edges_file_missing(tmp_path):
    path = write(tmp_path, """
        [social]
        edges = "nope.csv"
        [agents]
        measure = [["1"]]
    """)
    with pytest.raises(ScenarioError, match=r"social.edges: cannot read .*nope.csv"):
        load_scenario(path)


def test_not_toml_and_unknown_builtin(tmp_path):
    path = write(tmp_path, "this is = = not toml")
    with pytest.raises(ScenarioError, match="not valid TOML"):
        load_scenario(path)
    with pytest.raises(ScenarioError, match="no built-in scenario of that name"):
        load_scenario("no-such-scenario")


def test_sampson_edges_with_absolute_path(tmp_path, sampson_edges):
    path = write(tmp_path, f"""
        name = "sampson"
        [social]
        edges = "{sampson_edges}"
        self_weight = true
        seed = 3
        spectral_radius = 1.1
        process_noise = 0.1
        [agents]
        measure = [["1"], ["5"], ["12"], ["18"]]
        measurement_noise = 0.1
        [network]
        topology = "cycle"
        self_weight = 0.5
        max_delay = 5
        delay_seed = 1
    """)
    s = load_scenario(path)
    assert (s.n, s.N) == (18, 4)
    off = s.A.copy()
    np.fill_diagonal(off, 0)
    assert int((off != 0).sum()) == 88                      # README: 88 directed links
    assert np.all(np.diag(s.A) != 0)                        # self weights added
    assert s.rho_A == pytest.approx(1.1)
    # README: out-degree by id (row s,t means A[s,t] != 0: row sums of the pattern)
    assert ((off != 0).sum(axis=1)).tolist() == [6, 5, 5, 4, 5, 4, 5, 6, 4, 6, 5, 4, 3, 5, 6, 5, 4, 6]
    assert s.A[0, 1] != 0                                   # row "1,2": 1 listens to 2
    assert 0 <= s.delays.max() <= 5 and np.all(s.delays[s.W == 0] == 0)


FIELDS = ("name", "labels", "process_noise", "measure", "measurement_noise", "standby",
          "step_ms")


def assert_same_scenario(back, s):
    """Every field that defines a scenario, arrays bit for bit (not through digest())."""
    for f in FIELDS:
        assert getattr(back, f) == getattr(s, f), f
    for f in ("A", "W", "delays"):
        a, b = getattr(back, f), getattr(s, f)
        assert a.shape == b.shape and a.dtype.kind == b.dtype.kind and np.array_equal(a, b), f


def random_scenario(seed):
    rng = np.random.default_rng(seed)
    n, N = int(rng.integers(2, 9)), int(rng.integers(1, 5))
    A = np.where(rng.random((n, n)) < 0.5, rng.normal(size=(n, n)), 0.0)
    A[np.diag_indices(n)] = rng.uniform(0.1, 2.0, n) * rng.choice([-1, 1], n)
    A[0, 1] = 1e-300 if n > 1 else A[0, 1]              # extreme floats survive too
    W = rng.uniform(0.01, 1, (N, N))
    W /= W.sum(axis=1, keepdims=True)
    delays = rng.integers(0, 6, (N, N))
    np.fill_diagonal(delays, 0)
    labels = [f'n{i} "é\\ \t\x7f' for i in range(n)]   # quotes, accents, escapes
    return scenario_from_dict({
        "name": "random \U0001F600 #" + str(seed),
        "social": {"A": A.tolist(), "labels": labels, "process_noise": 0.1 * seed + 0.01},
        "agents": {"measure": [[labels[int(rng.integers(n))]] for _ in range(N)],
                   "measurement_noise": 0.3, "standby": int(rng.integers(0, 3))},
        "network": {"weights": W.tolist(), "delays": delays.tolist()},
        "runtime": {"step_ms": int(rng.integers(1, 100))},
    })


@pytest.mark.parametrize("make", [
    lambda: load_scenario("paper-14"),
    lambda: load_scenario("paper-14-live"),
    lambda: random_scenario(1),
    lambda: random_scenario(2),
    lambda: load_scenario("paper-14").replace(
        name='quote "me"', delays=np.array([[0, 2, 0], [0, 0, 1], [3, 0, 0]])),
], ids=["paper-14", "paper-14-live", "random-1", "random-2", "replaced"])
def test_scenario_to_toml_loads_back_equal(tmp_path, make):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RankDeficientWarning)
        s = make()
        path = tmp_path / "back.toml"
        path.write_text(scenario_to_toml(s), encoding="utf-8")
        back = load_scenario(path)
    assert_same_scenario(back, s)
    assert back.digest() == s.digest()



def test_a_broken_matrix_is_not_followed_by_label_problems_it_caused():
    """Until A is read, the node labels are unknown: measured labels are not called unknown."""
    bad = {"social": {"A": [[0.5, 0.1, 0.0], [0.0, 0.5], [0.1, 0.0, 0.5]]},
           "agents": {"measure": [["2"], ["3"]]}}
    with pytest.raises(ScenarioError) as info:
        scenario_from_dict(bad)
    assert info.value.problems == ["social.A: rows have different lengths [2, 3]"]
