"""Recovery planning: paper-14, the policy on hand cases, augmentation vs brute force."""

import itertools
import json

import networkx as nx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.cli.main import main
from design.connectivity import (
    agent_components,
    agent_flow_graph,
    is_strongly_connected,
    strong_connectivity_augmentation,
)
from design.graph import condensation
from design.recovery import (
    RecoveryError,
    failure_tolerance,
    is_recoverable,
    plan_recovery,
    redundancy_tolerance,
)
from design.scenario import scenario_from_dict

# ---------------------------------------------------------------------------------
# paper-14


def test_paper14_fail_1_and_2(paper14):
    s = paper14
    plan = plan_recovery(s, [0, 1])
    lab = s.labels
    assert {a: [lab[v] for v in c] for a, c in plan.candidates.items()} == {0: ["6", "8"], 1: ["10", "11"]}
    reps = [(r.failed, lab[r.node_from], lab[r.node_to], r.by, r.by_standby) for r in plan.replacements]
    assert reps == [(0, "7", "8", 4, True), (1, "9", "10", 3, False)]
    assert plan.agent_ids == [4, 3]                      # standby 4 sits in agent 1's row
    np.testing.assert_allclose(plan.W_removed, [[1.0, 0.0], [0.5, 0.5]])
    assert not plan.network_strongly_connected_removed
    assert plan.components_removed == [[4], [3]]
    assert plan.added_links == [(3, 4)]                  # one link: 4 listens to 3
    np.testing.assert_allclose(plan.W_after, [[0.5, 0.5], [0.5, 0.5]])
    assert plan.network_strongly_connected_after
    assert [[lab[v] for v in m] for m in plan.measure_after] == [["8"], ["12", "10"]]
    new = plan.scenario_after
    assert new is not None and new.N == 2 and new.standby == 0
    assert plan.numerical["observable_after"] and plan.numerical["observability_rank_after"] == 14
    assert plan.numerical["distributed_detectable_after"]
    d = plan.to_dict(s)
    assert d["replacements"]["1"] == {"from": "7", "to": "8", "by": 4, "by_standby": True}
    assert d["replacements"]["2"] == {"from": "9", "to": "10", "by": 3, "by_standby": False}
    assert d["added_links"] == [{"from": 3, "to": 4}]


@pytest.mark.parametrize("f, node_to", [(0, "8"), (1, "10"), (2, "13")])
def test_paper14_single_failure_standby_takes_the_place(paper14, f, node_to):
    plan = plan_recovery(paper14, [f])
    (r,) = plan.replacements
    assert r.by == 4 and r.by_standby and paper14.labels[r.node_to] == node_to
    assert plan.added_links == [] and plan.network_strongly_connected_removed
    np.testing.assert_allclose(plan.W_after, paper14.W)   # same place, same links and weights
    assert plan.agent_ids[f] == 4


def test_a_plan_without_the_numerical_checks_gives_the_same_next_configuration(paper14):
    """``numerical=False`` (what the monitor asks: the checks are a staircase of order nN,
    seconds at communities-32) builds the same next scenario, and only the numbers are
    left out; replan's next roster is the same either way."""
    from design.roster import Roster, replan

    for failed in ([0], [1, 2], [0, 1, 2]):
        full, bare = plan_recovery(paper14, failed), plan_recovery(paper14, failed,
                                                                   numerical=False)
        assert full.numerical and bare.numerical == {}
        assert (full.scenario_after is None) == (bare.scenario_after is None)
        if full.scenario_after is not None:
            for name in ("W", "delays", "measure", "standby", "name"):
                a, b = getattr(full.scenario_after, name), getattr(bare.scenario_after, name)
                assert np.array_equal(np.asarray(a, dtype=object), np.asarray(b, dtype=object))
    r = Roster.initial(paper14)
    for a in r.ids:
        (_, full), (_, bare) = replan(r, [a]), replan(r, [a], numerical=False)
        assert (full.ids, full.standby_ids) == (bare.ids, bare.standby_ids)
        assert np.array_equal(full.delays, bare.delays)
        assert full.scenario.measure == bare.scenario.measure


def test_paper14_tolerances(paper14):
    ft = failure_tolerance(paper14)
    assert (ft.p, ft.exact, ft.witness) == (1, True, (0, 1))
    assert failure_tolerance(paper14, allow_new_links=True).p == 3
    assert redundancy_tolerance(paper14).p == 0


# ---------------------------------------------------------------------------------
# the policy on small hand cases


def scenario(A, measure, topology="cycle", standby=0, weights=None, delays=None):
    net = {"weights": weights} if weights is not None else {"topology": topology, "self_weight": 0.5}
    if delays is not None:
        net["delays"] = delays
    return scenario_from_dict({
        "social": {"A": A},
        "agents": {"measure": measure, "standby": standby},
        "network": net,
    })


# nodes 1, 2 form a child SCC feeding the parent cycle {3, 4, 5}; node 6 is a parent alone
A6 = np.diag([0.5, 0.6, 0.7, 0.8, 0.9, 0.4])
A6[1, 0] = A6[0, 1] = 0.3          # {1, 2}
A6[2, 1] = 0.2                     # 2 -> 3
A6[3, 2] = A6[4, 3] = A6[2, 4] = 0.5   # 3 -> 4 -> 5 -> 3
A6[5, 0] = 0.1                     # 1 -> 6
A6 = A6.tolist()


def test_child_node_has_no_equivalent_and_singleton_parent_is_unrecoverable():
    s = scenario(A6, [["1", "3"], ["6"], ["4"]])
    plan = plan_recovery(s, [0])
    assert plan.no_equivalent == {0: [0]}                # node 1 is in a child SCC
    assert [s.labels[v] for v in plan.candidates[0]] == ["4", "5"]
    (r,) = plan.replacements                             # 3 -> 5 (4 is measured already)
    assert s.labels[r.node_to] == "5"
    # no standby: the survivor with fewest nodes takes it (tie 2 vs 3: lowest id)
    assert r.by == 2 and not r.by_standby
    assert plan.is_recoverable(True)
    plan = plan_recovery(s, [1])                         # the only sensor of {6} fails
    assert plan.unrecoverable == {1: [5]} and plan.replacements == []
    assert not plan.structurally_observable_after and not plan.is_recoverable(True)
    assert plan.to_dict(s)["unmeasured_parent_sccs_after"] == [["6"]]


def test_nearest_candidate_along_influence_edges():
    # parent cycle 3 -> 4 -> 5 -> 3: losing 3, node 4 hears it first
    s = scenario(A6, [["3", "6"], ["6"]])
    plan = plan_recovery(s, [0])
    assert [s.labels[r.node_to] for r in plan.replacements] == ["4"]


def test_removed_agent_rows_renormalised_and_new_link_weights():
    W = [[0.6, 0.4, 0.0, 0.0],
         [0.0, 0.5, 0.25, 0.25],
         [0.0, 0.0, 0.7, 0.3],
         [0.2, 0.0, 0.0, 0.8]]
    D = [[0, 2, 0, 0], [0, 0, 1, 3], [0, 0, 0, 4], [1, 0, 0, 0]]
    s = scenario(A6, [["3", "6"], ["4"], ["5"], ["6"]], weights=W, delays=D)
    plan = plan_recovery(s, [0])          # agent 1 fails, no standby; node 3 goes elsewhere
    assert plan.agent_ids == [2, 3, 4]
    np.testing.assert_allclose(plan.W_removed, [[0.5, 0.25, 0.25], [0, 0.7, 0.3], [0, 0, 1.0]])
    # flow: 3 -> 2, 4 -> 2, 4 -> 3; agent 4 hears no one: one link into 4 from a sink SCC
    assert len(plan.added_links) == 1 and plan.added_links[0][1] == 4
    frm = plan.added_links[0][0]
    row = plan.W_after[2]
    assert row[2] == pytest.approx(0.8)                  # agent 4 keeps its scenario self weight
    assert row[plan.agent_ids.index(frm)] == pytest.approx(0.2)
    assert plan.delays_after[2, plan.agent_ids.index(frm)] == 4   # new link: largest delay
    np.testing.assert_array_equal(plan.delays_after[:2, :2], [[0, 1], [0, 0]])
    assert plan.network_strongly_connected_after and plan.scenario_after is not None


def test_no_new_links_leaves_the_network_split():
    s = scenario(A6, [["3", "6"], ["4"], ["6"]])
    plan = plan_recovery(s, [1], add_links=False)
    assert plan.added_links == [] and not plan.network_strongly_connected_after
    assert plan.scenario_after is None and not plan.is_recoverable(False)
    assert plan.is_recoverable(True)         # links could restore it


def test_bad_failure_lists(paper14):
    with pytest.raises(RecoveryError, match="no agent 4 \\(agents are 1..3\\)"):
        plan_recovery(paper14, [3])
    with pytest.raises(RecoveryError, match="agent 1 listed twice"):
        plan_recovery(paper14, [0, 0])
    with pytest.raises(RecoveryError, match="integers"):
        is_recoverable(paper14, ["1"])


def test_tolerance_complete_network_and_redundant_sensors():
    cyc = [[0.5, 0.5, 0.0], [0.0, 0.5, 0.5], [0.5, 0.0, 0.5]]   # parent cycle {1, 2, 3}
    s = scenario(cyc, [["1"], ["2"], ["3"]], topology="complete")
    assert redundancy_tolerance(s).p == 2
    assert failure_tolerance(s).p == 2 and failure_tolerance(s).witness == (0, 1, 2)
    s1 = scenario(cyc, [["1"], ["2"], ["3"]], topology="complete", standby=1)
    assert failure_tolerance(s1).p == 3                      # even all three: the standby
    s4 = scenario(cyc, [["1"], ["2"], ["3"], ["1"]], topology="cycle")
    assert failure_tolerance(s4).p == 0                      # a broken cycle is a path
    assert failure_tolerance(s4, allow_new_links=True).p == 3


@settings(max_examples=40, deadline=None)
@given(st.integers(2, 6), st.integers(0, 2**31 - 1), st.integers(0, 2))
def test_failure_tolerance_definition(N, seed, standby):
    rng = np.random.default_rng(seed)
    W = (rng.random((N, N)) < 0.5) * rng.uniform(0.1, 1, (N, N))
    W[np.arange(N), (np.arange(N) + 1) % N] += 0.5           # a cycle keeps it strongly connected
    np.fill_diagonal(W, rng.uniform(0.1, 1, N))
    W = (W / W.sum(axis=1, keepdims=True)).tolist()
    nodes = ["3", "4", "5", "6"]
    measure = [[nodes[rng.integers(0, 4)]] for _ in range(N)]
    s = scenario(A6, measure, weights=W, standby=standby)
    for links in (False, True):
        ft = failure_tolerance(s, allow_new_links=links)
        p = -1 if ft.p is None else ft.p
        for size in range(0, p + 1):
            for sub in itertools.combinations(range(N), size):
                assert is_recoverable(s, sub, allow_new_links=links)
        if ft.witness is not None:
            assert len(ft.witness) == p + 1 and not is_recoverable(s, ft.witness, links)
        else:
            assert ft.p == N


# ---------------------------------------------------------------------------------
# strong-connectivity augmentation: fewest links, checked by brute force


def _strong_bitmask(out_mask, in_mask, n) -> bool:
    """Strong connectivity from adjacency bitmasks: node 0 reaches all, all reach node 0."""
    full = (1 << n) - 1
    for adj in (out_mask, in_mask):
        seen, frontier = 1, 1
        while frontier:
            nxt = 0
            for u in range(n):
                if frontier >> u & 1:
                    nxt |= adj[u]
            frontier = nxt & ~seen
            seen |= nxt
        if seen != full:
            return False
    return True


def brute_force_min_links(M) -> int:
    """Fewest new edges making M strongly connected, by trying every edge set in size order."""
    n = M.shape[0]
    out0 = [sum(1 << v for v in range(n) if M[u, v]) for u in range(n)]
    in0 = [sum(1 << u for u in range(n) if M[u, v]) for v in range(n)]
    if n <= 1 or _strong_bitmask(out0, in0, n):
        return 0
    missing = [(u, v) for u in range(n) for v in range(n) if u != v and not M[u, v]]
    for k in range(1, len(missing) + 1):
        for S in itertools.combinations(missing, k):
            out, inn = out0[:], in0[:]
            for u, v in S:
                out[u] |= 1 << v
                inn[v] |= 1 << u
            if _strong_bitmask(out, inn, n):
                return k
    raise AssertionError("a complete digraph is strongly connected")


@settings(max_examples=150, deadline=None)
@given(st.integers(1, 5), st.floats(0.0, 0.6), st.integers(0, 2**31 - 1))
def test_augmentation_is_minimal_and_correct(n, density, seed):
    rng = np.random.default_rng(seed)
    M = (rng.random((n, n)) < density).astype(int)
    np.fill_diagonal(M, 0)
    added = strong_connectivity_augmentation(M)
    M2 = M.copy()
    for u, v in added:
        assert u != v and not M[u, v]
        M2[u, v] = 1
    assert n == 1 or is_strongly_connected(M2)
    assert len(added) == brute_force_min_links(M)
    # the Eswaran-Tarjan count max(s, t) + q (isolated SCCs counted apart)
    C = condensation(M)
    if C.k > 1:
        iso = set(C.sources) & set(C.sinks)
        s, t = len(set(C.sources) - iso), len(set(C.sinks) - iso)
        assert len(added) == max(s, t) + len(iso)


def test_augmentation_larger_graphs_reach_the_lower_bound():
    rng = np.random.default_rng(11)
    for _ in range(30):
        n = int(rng.integers(10, 60))
        M = (rng.random((n, n)) < rng.uniform(0.0, 0.08)).astype(int)
        np.fill_diagonal(M, 0)
        added = strong_connectivity_augmentation(M)
        M2 = M.copy()
        for u, v in added:
            M2[u, v] = 1
        assert is_strongly_connected(M2)
        C = condensation(M)
        if C.k > 1:
            iso = set(C.sources) & set(C.sinks)
            assert len(added) == max(len(set(C.sources) - iso), len(set(C.sinks) - iso)) + len(iso)


def test_agent_flow_graph_orientation():
    W = np.array([[0.5, 0.5, 0], [0, 1.0, 0], [0, 0.5, 0.5]])   # 1 and 3 listen to 2
    M = agent_flow_graph(W)
    assert M[1, 0] == 1 and M[1, 2] == 1 and M.sum() == 2
    added = strong_connectivity_augmentation(M)      # source {2}, sinks {1}, {3}: 2 links
    assert len(added) == 2
    for u, v in added:
        M[u, v] = 1
    assert is_strongly_connected(M)


# ---------------------------------------------------------------------------------
# CLI

PLAN_KEYS = {"candidates", "replacements", "observable_after", "network_strongly_connected_after",
             "added_links", "W_after", "measure_after", "agents_after", "recoverable"}


def test_cli_plan_paper14_json(capsys):
    assert main(["plan", "paper-14", "--fail", "1,2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert PLAN_KEYS <= set(d)
    assert "8" in d["candidates"]["1"] and "6" in d["candidates"]["1"]
    assert "10" in d["candidates"]["2"] and "11" in d["candidates"]["2"]
    assert d["replacements"]["1"]["to"] == "8" and d["replacements"]["2"]["to"] == "10"
    assert d["observable_after"] and d["network_strongly_connected_after"]


def test_cli_plan_text_and_written_scenario(tmp_path, capsys):
    out = tmp_path / "rec.toml"
    assert main(["plan", "paper-14", "--fail", "1,2", "--write-scenario", str(out)]) == 0
    text = capsys.readouterr().out
    assert "node 7 -> node 8, measured by standby agent 4" in text
    assert "3 -> 4 (agent 4 listens to 3)" in text
    assert "measure after: agent 4: 8; agent 3: 12, 10" in text
    assert main(["analyze", str(out), "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["measure"] == [["8"], ["12", "10"]] and d["observable"]


def test_a_singular_w_after_is_said_and_costs_no_stability(paper14, capsys):
    """Agents 1 and 2 failing on paper-14 leave agents 4 and 3 with the rows (0.5, 0.5):
    W after is singular. The modes it adds to W (x) A are at 0 (the pair stays
    detectable), a gain designed for the configuration is certified stable by the exact
    radius, and plan says what the singular W means beside "recoverable: yes"; with a
    full-rank W after (agent 1 alone failing) it says nothing of it."""
    from design.closed_loop import closed_loop_for
    from design.gain_design import design_gains

    assert main(["plan", "paper-14", "--fail", "1,2", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["W_after"] == [[0.5, 0.5], [0.5, 0.5]] and d["rank_W_after"] == 1
    assert d["distributed_detectable_after"] is True
    assert max(m["abs"] for m in d["distributed_unobservable_modes_after"]) < 1e-12
    new = plan_recovery(paper14, [0, 1]).scenario_after
    G = design_gains(new, exact_mse=False, starts=1, max_iter=30, gaps=False).G
    assert closed_loop_for(new, G, new.delays).spectral_radius() < 1
    assert main(["plan", "paper-14", "--fail", "1,2"]) == 0
    text = capsys.readouterr().out
    assert "  W after is singular (rank 1 of 2): W (x) A gets modes at 0, which vanish in " \
           "one step" in text and "no stability is lost" in text
    assert text.rstrip().endswith("recoverable: yes")
    assert main(["plan", "paper-14", "--fail", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rank_W_after"] == 3
    assert main(["plan", "paper-14", "--fail", "1"]) == 0
    assert "singular" not in capsys.readouterr().out


@pytest.mark.parametrize("fail, message", [
    ("5", "--fail: no agent 5 (agents are 1..3)"),
    ("0", "--fail: no agent 0"),
    ("1,x", "--fail: agent ids are positive integers, got 'x'"),
    ("2,2", "--fail: agent 2 listed twice"),
    ("", "--fail: give at least one agent"),
])
def test_cli_plan_bad_fail_list_exits_2(capsys, fail, message):
    assert main(["plan", "paper-14", "--fail", fail]) == 2
    assert message in capsys.readouterr().err


def test_cli_plan_negative_result_exits_1(tmp_path, capsys):
    path = tmp_path / "s.toml"
    path.write_text(f'[social]\nA = {A6}\n[agents]\nmeasure = [["3", "6"], ["6"], ["4"]]\n')
    # agents 1 and 2 are the only sensors of the single-node parent SCC {6}
    assert main(["plan", str(path), "--fail", "1,2", "--json"]) == 1
    d = json.loads(capsys.readouterr().out)
    assert d["recoverable"] is False and d["unmeasured_parent_sccs_after"] == [["6"]]


def test_sccs_condensation_and_strong_connectivity_against_networkx():
    """One SCC path (graph.canonical_components) checked against networkx's own."""
    rng = np.random.default_rng(3)
    for _ in range(40):
        n = int(rng.integers(1, 25))
        W = (rng.random((n, n)) < rng.uniform(0.02, 0.3)) * rng.uniform(0.1, 1, (n, n))
        np.fill_diagonal(W, 1.0)
        G = nx.DiGraph()
        G.add_nodes_from(range(n))
        G.add_edges_from((j, i) for i, j in zip(*np.nonzero(W)) if i != j)  # j -> i
        theirs = sorted(sorted(c) for c in nx.strongly_connected_components(G))
        assert agent_components(W) == theirs          # sorted by smallest agent already
        assert is_strongly_connected(agent_flow_graph(W)) == nx.is_strongly_connected(G)
        C = condensation(agent_flow_graph(W))
        dag = nx.condensation(G)
        assert C.dag.nnz == dag.number_of_edges()
        assert len(C.sinks) == sum(1 for v in dag if dag.out_degree(v) == 0)
