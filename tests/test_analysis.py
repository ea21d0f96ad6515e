"""Structural and numerical analysis: hand cases, paper-14 facts, properties, CLI."""

import json
from fractions import Fraction

import networkx as nx
import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st

from agent.cli.main import main
from design.analysis import analyze, structural_analysis
from design.graph import influence_structure
from design.observability import distributed_detectability, observability_rank, unobservable_modes
from design.scenario import scenario_from_dict

# ---------------------------------------------------------------------------------
# hand-computed small cases


def test_chain_structure_and_modes():
    # 1 -> 2 -> 3 (2 listens to 1, 3 listens to 2); parent SCC = {3}
    A = np.array([[0.5, 0, 0], [1, 2.0, 0], [0, 1, 0.3]])
    s = structural_analysis(A, measured=[1])
    assert s.structure.components == [[0], [1], [2]]
    assert s.parents == [2] and s.children == [0, 1]
    assert s.unmeasured_parents == [2] and not s.structurally_observable
    assert s.minimal_sensor_set == [2]
    # measuring node 2: observable part = states 1, 2; unobservable mode a_33 = 0.3
    C2 = np.array([[0, 1.0, 0]])
    assert observability_rank(A, C2) == 2
    np.testing.assert_allclose(unobservable_modes(A, C2), [0.3])
    # measuring node 1 sees only itself: modes 2 (unstable) and 0.3
    np.testing.assert_allclose(sorted(unobservable_modes(A, np.array([[1.0, 0, 0]]))), [0.3, 2.0])
    assert unobservable_modes(A, np.array([[0, 0, 1.0]])).size == 0


def star_scenario(self_loops: bool):
    # node 1 listens to 2 and 3, they listen to 1: one parent SCC {1, 2, 3}
    if self_loops:
        A = [[0.4, 1.0, 1.0], [1.0, 0.7, 0.0], [1.0, 0.0, 0.2]]
    else:  # nodes 2 and 3 both only listen to 1: a "dilation", rank(A) = 2
        A = [[0.0, 1.0, 1.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    return scenario_from_dict({"social": {"A": A}, "agents": {"measure": [["1"]]}})


def test_missing_self_loops_break_the_structural_verdict():
    with pytest.warns(UserWarning, match="rank 2 < n = 3"):
        s = star_scenario(self_loops=False)
    r = analyze(s)
    # C = e1, CA = [0, 1, 1], CA^2 = [2, 0, 0]: rank 2; A (e2 - e3) = 0: mode 0
    assert r.structurally_observable and r.observability_rank == 2 and not r.observable
    assert not r.verdicts_agree
    (reason,) = [x for x in r.reasons() if x.startswith("(A, H)")]
    assert "numerical rank 2 of 3" in reason
    assert "A has rank 2 < n = 3" in reason and "a_ii = 0): 1..3" in reason
    assert r.to_dict()["missing_self_loops"] == ["1", "2", "3"]
    np.testing.assert_allclose(r.unobservable_modes, [0.0], atol=1e-12)
    assert r.detectable
    # PBH: the mode is an eigenvalue where [A - lam I; C] loses rank
    M = np.vstack([s.A - r.unobservable_modes[0] * np.eye(3), s.H_all])
    assert np.linalg.matrix_rank(M, tol=1e-9) < 3


def test_self_loops_restore_agreement():
    r = analyze(star_scenario(self_loops=True))
    assert r.observable and r.verdicts_agree and r.distributed_verdicts_agree
    assert r.reasons() == []


# ---------------------------------------------------------------------------------
# paper-14


def test_paper14_facts(paper14):
    r = analyze(paper14)
    d = r.to_dict()
    assert round(d["rho_A"], 4) == 1.0857 and d["full_rank"]
    assert d["sccs"] == [
        {"nodes": ["1", "2", "3", "4", "5"], "parent": False},
        {"nodes": ["6", "7", "8"], "parent": True},
        {"nodes": ["9", "10", "11"], "parent": True},
        {"nodes": ["12", "13", "14"], "parent": True},
    ]
    assert d["equivalence_classes"] == [["6", "7", "8"], ["9", "10", "11"], ["12", "13", "14"]]
    assert d["minimal_sensor_set"] == ["7", "9", "12"]
    assert d["observable"] and d["observability_rank"] == 14 and d["detectable"]
    # the distributed pair: rank 33 of 42, 9 stable unobservable modes (BRIEF facts)
    assert d["distributed_rank"] == 33 and not d["distributed_observable"]
    assert len(d["distributed_unobservable_modes"]) == 9
    assert max(m["abs"] for m in d["distributed_unobservable_modes"]) == pytest.approx(0.2263, abs=1e-4)
    assert d["distributed_detectable"]
    assert d["distributed_structurally_observable"] and not d["distributed_verdicts_agree"]
    assert "6..14" in d["disagreement_reasons"][0]
    assert d["network_strongly_connected"]
    assert d["failure_tolerance"] == 1 and d["failure_tolerance_witness"] == [1, 2]
    assert d["failure_tolerance_without_replacement"] == 0


def test_paper14_distributed_modes_by_pbh(paper14):
    s = paper14
    WA = np.kron(s.W, s.A)
    modes = unobservable_modes(WA, s.D_H)
    for lam in modes:
        M = np.vstack([WA - lam * np.eye(42), s.D_H])
        assert np.linalg.svd(M, compute_uv=False)[-1] < 1e-8
    # a stable eigenvalue of WA that is NOT unobservable: PBH has full rank there
    other = [v for v in np.linalg.eigvals(WA) if np.min(np.abs(modes - v)) > 1e-3][0]
    M = np.vstack([WA - other * np.eye(42), s.D_H])
    assert np.linalg.svd(M, compute_uv=False)[-1] > 1e-6


# ---------------------------------------------------------------------------------
# properties


@st.composite
def digraphs(draw, max_n=9):
    n = draw(st.integers(1, max_n))
    density = draw(st.floats(0.0, 0.6))
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    A = (rng.random((n, n)) < density) * rng.uniform(0.5, 1.5, (n, n))
    return A


def _edges_leaving(A, comp):
    comp = set(comp)
    return [(j, i) for i in range(A.shape[0]) for j in comp if A[i, j] != 0 and i not in comp and i != j]


@settings(max_examples=80, deadline=None)
@given(digraphs())
def test_sccs_partition_and_parents_are_sinks(A):
    s = structural_analysis(A)
    comps = s.structure.components
    nodes = sorted(v for c in comps for v in c)
    assert nodes == list(range(A.shape[0]))
    for c, comp in enumerate(comps):
        assert all(s.structure.labels[v] == c for v in comp)
        leaving = _edges_leaving(A, comp)
        assert (c in s.parents) == (not leaving)
    # equivalence classes (parents) are unions of whole SCCs
    for c in s.parents:
        cls = set(comps[c])
        assert all(set(comp) <= cls or not set(comp) & cls for comp in comps)
    # the minimal sensor set makes the pair structurally observable with |parents| nodes
    t = structural_analysis(A, s.minimal_sensor_set)
    assert t.structurally_observable and len(s.minimal_sensor_set) == len(s.parents)


@settings(max_examples=80, deadline=None)
@given(digraphs(max_n=12))
def test_sccs_match_networkx(A):
    G = nx.DiGraph()
    G.add_nodes_from(range(A.shape[0]))
    G.add_edges_from((j, i) for i, j in zip(*np.nonzero(A)) if i != j)
    ours = sorted(map(tuple, influence_structure(A).components))
    theirs = sorted(tuple(sorted(c)) for c in nx.strongly_connected_components(G))
    assert ours == theirs
    cond = nx.condensation(G)
    sinks = sorted(tuple(sorted(cond.nodes[c]["members"])) for c in cond if cond.out_degree(c) == 0)
    s = structural_analysis(A)
    assert sorted(tuple(s.structure.components[c]) for c in s.parents) == sinks


def _exact_rank(rows) -> int:
    M = [[Fraction(int(x)) for x in r] for r in rows]
    rank, col, ncols = 0, 0, len(M[0]) if M else 0
    while rank < len(M) and col < ncols:
        piv = next((r for r in range(rank, len(M)) if M[r][col] != 0), None)
        if piv is None:
            col += 1
            continue
        M[rank], M[piv] = M[piv], M[rank]
        for r in range(len(M)):
            if r != rank and M[r][col] != 0:
                f = M[r][col] / M[rank][col]
                M[r] = [a - f * b for a, b in zip(M[r], M[rank])]
        rank += 1
        col += 1
    return rank


@st.composite
def small_systems(draw):
    n = draw(st.integers(1, 6))
    A = np.array(draw(st.lists(st.lists(st.sampled_from([-1, 0, 0, 0, 1, 2]), min_size=n, max_size=n),
                               min_size=n, max_size=n)), dtype=float)
    p = draw(st.integers(1, 2))
    C = np.array(draw(st.lists(st.lists(st.sampled_from([0, 0, 1, -1]), min_size=n, max_size=n),
                               min_size=p, max_size=p)), dtype=float)
    return A, C


@settings(max_examples=150, deadline=None)
@given(small_systems())
def test_staircase_rank_matches_exact_reference(sys_):
    A, C = sys_
    n = A.shape[0]
    blocks, M = [], C.copy()
    for _ in range(n):  # plain reference: [C; CA; ...; CA^(n-1)], exact integer rank
        blocks.append(M)
        M = M @ A
    O = np.vstack(blocks)
    assert observability_rank(A, C) == _exact_rank(O.astype(int).tolist())
    assert unobservable_modes(A, C).size == n - observability_rank(A, C)


@settings(max_examples=60, deadline=None)
@given(small_systems(), st.randoms(use_true_random=False))
def test_observability_rank_invariant_under_relabelling(sys_, rnd):
    A, C = sys_
    n = A.shape[0]
    perm = list(range(n))
    rnd.shuffle(perm)
    P = np.eye(n)[perm]
    assert observability_rank(P @ A @ P.T, C @ P.T) == observability_rank(A, C)
    m1 = np.sort_complex(unobservable_modes(A, C).astype(complex))
    m2 = np.sort_complex(unobservable_modes(P @ A @ P.T, C @ P.T).astype(complex))
    # a defective eigenvalue (Jordan block of size m) moves by eps^(1/m) under rounding:
    # up to ~1e-4 for n <= 4 (found: a double eigenvalue 0 computed as +-8e-9 and as
    # +-8e-9 i); a relabelling bug would move modes by O(1)
    assert m1.shape == m2.shape
    cost = np.abs(m1[:, None] - m2[None, :])
    from scipy.optimize import linear_sum_assignment
    rows, cols = linear_sum_assignment(cost)
    assert np.all(cost[rows, cols] < 1e-3 * max(1.0, np.abs(A).max()))


def test_structural_analysis_on_sparse_graph_never_densifies():
    # n = 1 million nodes: a dense A would need 8 TB, so this only passes if A stays sparse
    n, m = 1_000_000, 100_000
    rng = np.random.default_rng(5)
    rows, cols = rng.integers(0, n, m), rng.integers(0, n, m)
    A = sp.csr_matrix((np.ones(m), (rows, cols)), shape=(n, n))
    s = structural_analysis(A, measured=[0, 1])
    assert s.structure.components.sizes().sum() == n
    assert len(s.minimal_sensor_set) == len(s.parents)
    assert s.missing_self_loops.size == n - np.unique(rows[rows == cols]).size
    assert s.n_sccs == len(s.structure.components) and s.structure.components[0][0] == 0


def test_sparse_and_dense_structural_analysis_agree():
    rng = np.random.default_rng(2)
    A = (rng.random((40, 40)) < 0.06) * 1.0
    d, s = structural_analysis(A, [3, 7]), structural_analysis(sp.csr_matrix(A), [3, 7])
    assert d.structure.components == s.structure.components
    assert d.parents == s.parents and d.minimal_sensor_set == s.minimal_sensor_set
    assert d.unmeasured_parents == s.unmeasured_parents
    assert d.missing_self_loops.tolist() == s.missing_self_loops.tolist()


# ---------------------------------------------------------------------------------
# CLI

ANALYZE_KEYS = {
    "rho_A", "full_rank", "sccs", "observable", "observability_rank", "distributed_observable",
    "distributed_rank", "equivalence_classes", "network_strongly_connected", "failure_tolerance",
    "A", "W", "delays", "measure", "minimal_sensor_set", "detectable", "distributed_detectable",
    "unobservable_modes", "distributed_unobservable_modes", "verdicts_agree",
    "distributed_verdicts_agree", "disagreement_reasons",
}


def test_cli_analyze_json(capsys):
    assert main(["analyze", "paper-14", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert ANALYZE_KEYS <= set(d)
    assert d["measure"] == [["7"], ["9"], ["12"]]
    assert np.array(d["A"]).shape == (14, 14) and np.array(d["W"]).shape == (3, 3)


def test_cli_analyze_text(capsys):
    assert main(["analyze", "paper-14"]) == 0
    out = capsys.readouterr().out
    assert "parent {6, 7, 8}" in out and "numerical rank 33 of 42" in out
    assert "failure tolerance" in out


def test_cli_analyze_bad_scenario_exits_2(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text('[social]\nA = [[1.0, 2.0]]\n[agents]\nmeasure = [["1"]]\n')
    assert main(["analyze", str(path)]) == 2
    err = capsys.readouterr().err
    assert "bad scenario" in err and "social.A: must be square, got 1 x 2" in err
    assert main(["analyze", "no-such-thing"]) == 2
    assert "no built-in scenario" in capsys.readouterr().err


def test_cli_analyze_rank_deficient_warns_on_stderr(tmp_path, capsys):
    path = tmp_path / "rd.toml"
    path.write_text('[social]\nA = [[1.0, 1.0], [1.0, 1.0]]\n[agents]\nmeasure = [["1"]]\n')
    assert main(["analyze", str(path), "--json"]) == 0
    cap = capsys.readouterr()
    assert "warning:" in cap.err and "rank 1 < n = 2" in cap.err
    d = json.loads(cap.out)
    assert d["full_rank"] is False and d["warnings"]


@pytest.mark.parametrize("self_weight, rank", [(0.5, 58), (0.6, 72)])
def test_sampson_even_cycle_with_half_self_weight_has_singular_W(tmp_path, sampson_edges,
                                                                   self_weight, rank):
    from design.scenario import load_scenario

    path = tmp_path / "sampson.toml"
    path.write_text(
        f'[social]\nedges = "{sampson_edges}"\nseed = 3\nspectral_radius = 1.1\n'
        '[agents]\nmeasure = [["1"], ["5"], ["12"], ["18"]]\n'
        f'[network]\ntopology = "cycle"\nself_weight = {self_weight}\n'
    )
    r = analyze(load_scenario(path))
    assert r.observable and len(r.equivalence_classes) == 1 and r.structural.n_sccs == 1
    # 0.5 I + 0.5 P with P a 4-cycle has eigenvalue 0: W (x) A loses rank, modes at 0
    assert r.distributed_rank == rank and r.distributed_detectable
    if rank < 72:
        assert np.max(np.abs(r.distributed_unobservable_modes)) < 1e-9
        assert "W has rank 3 < N = 4" in r.reasons()[0]
    else:
        assert r.reasons() == []


def test_distributed_detectability_against_the_textbook_tests():
    """Rank by the observability matrix, unobservable modes by the PBH test (small n N)."""
    rng = np.random.default_rng(5)
    seen = set()
    for trial in range(20):
        n, N = 4, 2
        A = (rng.random((n, n)) < 0.35) * rng.uniform(0.5, 2.0, size=(n, n))
        W = np.array([[0.6, 0.4], [0.5, 0.5]])
        measure = [[int(rng.integers(n))], [int(rng.integers(n))]]
        d = distributed_detectability(A, W, measure)
        WA = np.kron(W, A)
        C = np.zeros((2, n * N))
        C[0, measure[0][0]], C[1, n + measure[1][0]] = 1, 1
        O = np.vstack([C @ np.linalg.matrix_power(WA, k) for k in range(n * N)])
        assert d.rank == np.linalg.matrix_rank(O), trial
        hidden = [lam for lam in np.linalg.eigvals(WA)
                  if np.linalg.matrix_rank(np.vstack([WA - lam * np.eye(n * N), C]),
                                           tol=1e-8) < n * N]
        worst_pbh = max((abs(lam) for lam in hidden), default=0.0)
        assert d.max_unobservable_modulus == pytest.approx(worst_pbh, abs=1e-6), trial
        assert d.detectable == (worst_pbh < 1)
        seen.add((d.rank < n * N, d.detectable))
    assert seen == {(False, True), (True, True), (True, False)}  # every case is met


def test_distributed_detectable_without_the_staircase_agrees_with_it(monkeypatch):
    """The shortcut (every mode of W (x) A inside the unit circle: detectable, no
    staircase) and the staircase say the same on random pairs, stable and unstable A,
    stochastic and sub-stochastic W (a gap's), some nodes unmeasured; and the stable
    ones never reach the staircase."""
    from design import observability as ob

    rng = np.random.default_rng(11)
    seen = set()
    for trial in range(60):
        n, N = int(rng.integers(2, 6)), int(rng.integers(2, 4))
        A = (rng.random((n, n)) < 0.4) * rng.uniform(-1.0, 1.0, size=(n, n))
        rho = max(abs(np.linalg.eigvals(A))) or 1.0
        A *= rng.choice([0.5, 0.95, 1.05, 1.5]) / rho
        W = rng.random((N, N)) * (rng.random((N, N)) < 0.7) + np.eye(N)
        W /= W.sum(axis=1, keepdims=True)
        if trial % 3 == 0:
            W[0] *= 0.5                    # a gap's row: the failed neighbour's weight gone
        measure = [sorted(set(rng.integers(n, size=int(rng.integers(0, 2)) + 1).tolist()))
                   for _ in range(N)]
        ob._DETECTABILITY.clear()
        full = distributed_detectability(A, W, measure).detectable
        bound = ob.stable_modes_bound(A, W)
        assert bound >= max(abs(np.linalg.eigvals(np.kron(W, A)))) - 1e-12, trial
        ob._DETECTABILITY.clear()
        with monkeypatch.context() as m:
            if bound < 1 - 1e-9:           # the stable ones never reach the staircase
                m.setattr(ob, "distributed_detectability", _no_staircase)
            assert ob.distributed_detectable(A, W, measure) == full, trial
        seen.add((bound < 1, full))
    assert seen == {(True, True), (False, True), (False, False)}


def _no_staircase(*args, **kwargs):
    raise AssertionError("the staircase was run for a stable W (x) A")


@pytest.mark.parametrize("A, W, measure, error", [
    (np.diag([0.5, 0.9]), np.ones((2, 3)) / 3, [[0], [1]], ValueError),     # W not square
    (np.diag([0.5, 0.9]), np.eye(2), [[0], [5]], IndexError),             # no node 5
])
def test_distributed_detectable_rejects_a_malformed_pair_as_the_staircase_does(A, W, measure,
                                                                               error):
    from design import observability as ob

    with pytest.raises(error):
        ob.distributed_detectability(A, W, measure)
    with pytest.raises(error):
        ob.distributed_detectable(A, W, measure)
    # lists are matrices too
    assert ob.distributed_detectable([[0.5, 0.0], [0.0, 0.9]], [[1.0]], [[0]]) is True


def test_check_detectable_without_the_rank_and_the_recovery_designs():
    """``check_detectable(rank=False)`` on communities-32 (A stable, radius 0.95) answers
    without the staircase; paper-14 (A unstable) computes the rank either way, and a
    recovery design's gain is the same as the design that computed it."""
    from design.gain_design import check_detectable
    from design.reconfigure import fast_recovery_gains
    from design.scenario import load_scenario

    big = load_scenario("communities-32")
    quick = check_detectable(big, rank=False)
    assert quick.detectable and quick.rank is None and quick.order == big.n * big.N
    assert quick.to_dict()["max_unobservable_modulus"] is None
    paper = load_scenario("paper-14")
    assert check_detectable(paper, rank=False) == check_detectable(paper)
    assert check_detectable(paper).rank == 33
    live = load_scenario("paper-14-live")
    a = fast_recovery_gains(live, "uniform:3")
    b = fast_recovery_gains(live, "uniform:3", pair_rank=True)
    assert a.detectability["rank"] is None and b.detectability["rank"] == 33
    assert all(np.array_equal(x, y) for x, y in zip(a.G, b.G)) and a.rho == b.rho


def test_cli_analyze_exits_1_on_an_undetectable_scenario(tmp_path, capsys):
    """An unstable mode no agent sees (node 1 grows, only node 2 is measured): a negative
    result, exit 1, said on stderr; a detectable one exits 0."""
    path = tmp_path / "u.toml"
    path.write_text('[social]\nA = [[1.5, 0.0], [0.0, 0.5]]\n[agents]\nmeasure = [["2"]]\n')
    assert main(["analyze", str(path), "--json"]) == 1
    cap = capsys.readouterr()
    assert json.loads(cap.out)["distributed_detectable"] is False
    assert "not detectable" in cap.err
    path.write_text('[social]\nA = [[0.9, 0.0], [0.0, 0.5]]\n[agents]\nmeasure = [["2"]]\n')
    assert main(["analyze", str(path), "--json"]) == 0


UNMEASURED_PARENT = """name = "unobs"

[social]
A = [
  [0.5, 0.3, 0,   0,   0,   0,   0.2, 0  ],
  [0.4, 0.5, 0,   0,   0,   0,   0,   0  ],
  [0,   0,   0.6, 0.2, 0,   0,   0,   0.2],
  [0,   0,   0.5, 0.4, 0,   0,   0,   0  ],
  [0,   0,   0,   0,   0.7, 0.3, 0.1, 0  ],
  [0,   0,   0,   0,   0.2, 0.6, 0,   0  ],
  [0,   0,   0,   0,   0,   0,   0.5, 0.4],
  [0,   0,   0,   0,   0,   0,   0.3, 0.6],
]
labels = ["a","b","c","d","e","f","g","h"]
process_noise = 0.05

[agents]
measure = [["a"], ["c"], ["g"]]
measurement_noise = 0.05
standby = 1

[network]
weights = [[0.5, 0.5, 0.0],
           [0.0, 0.6, 0.4],
           [0.3, 0.0, 0.7]]
delays = [[0, 2, 0],
          [0, 0, 1],
          [3, 0, 0]]
"""


def test_analyze_and_design_agree_on_a_parent_scc_without_sensor(tmp_path, capsys):
    """{e, f} is a parent SCC nobody measures, its modes decay: detectable. analyze says
    so, and that design refuses such a network (it does, naming the SCC)."""
    path = tmp_path / "s.toml"
    path.write_text(UNMEASURED_PARENT)
    assert main(["analyze", str(path)]) == 0
    text = capsys.readouterr().out
    assert "parent SCCs without sensor: {e, f}" in text
    assert "stabilising gains exist; but the states of a parent SCC without sensor are " \
           "then estimated open loop, and `socmon design` refuses such a network" in text
    assert main(["design", str(path), "--out", str(tmp_path / "g.npz")]) == 2
    assert "parent SCC {e, f} has no sensor" in capsys.readouterr().err
