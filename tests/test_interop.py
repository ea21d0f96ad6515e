"""Interop: closed loops as python-control systems, graphs as networkx digraphs, checked
against socmon's own certificates and SCCs."""

import numpy as np
import pytest

from design.analysis import structural_analysis
from design.closed_loop import closed_loop_for
from design.connectivity import agent_components
from design.experiments import sampson_scenario
from design.interop import agent_digraph, closed_loop_ss, influence_digraph
from design.scenario import resolve_delays, scenario_from_dict

nx = pytest.importorskip("networkx", reason="networkx is not installed (pip install "
                                             "'socmon[networkx]')")


def _control():
    return pytest.importorskip("control", reason="python-control is not installed (pip "
                                                 "install 'socmon[control]')")


def _parent_sccs(scenario) -> set:
    st = structural_analysis(scenario.A)
    return {frozenset(scenario.labels[v] for v in st.structure.components[c])
            for c in st.parents}


# -- networkx ---------------------------------------------------------------------------------

def test_parent_sccs_are_networkx_attracting_components_paper14(paper14):
    g = influence_digraph(paper14)
    assert g.number_of_nodes() == 14 and g.number_of_edges() == np.count_nonzero(paper14.A)
    assert g["1"]["6"]["weight"] == paper14.A[5, 0]       # 1 influences 6: A[6, 1] != 0
    assert not g.has_edge("6", "1")
    attracting = {frozenset(c) for c in nx.attracting_components(g)}
    assert attracting == _parent_sccs(paper14) == {
        frozenset({"6", "7", "8"}), frozenset({"9", "10", "11"}), frozenset({"12", "13", "14"})}
    sccs = {frozenset(c) for c in nx.strongly_connected_components(g)}
    st = structural_analysis(paper14.A)
    assert sccs == {frozenset(paper14.labels[v] for v in c) for c in st.structure.components}


@pytest.mark.parametrize("seed", [0, 3])
def test_parent_sccs_are_networkx_attracting_components_sampson(sampson_edges, seed):
    s = sampson_scenario(sampson_edges, seed=seed)
    attracting = {frozenset(c) for c in nx.attracting_components(influence_digraph(s))}
    assert attracting == _parent_sccs(s)
    assert len(attracting) >= 1


def test_influence_digraph_of_a_bare_sparse_matrix():
    import scipy.sparse as sp

    A = sp.csr_matrix(np.array([[0.5, 0.2, 0.0], [0.0, 0.5, 0.0], [0.0, 0.3, 0.1]]))
    g = influence_digraph(A, labels=["a", "b", "c"])
    assert set(g.edges()) == {("a", "a"), ("b", "a"), ("b", "b"), ("b", "c"), ("c", "c")}
    assert [sorted(c) for c in nx.attracting_components(g)] in (
        [["a"], ["c"]], [["c"], ["a"]])
    with pytest.raises(ValueError, match="labels: 2 labels for 3 nodes"):
        influence_digraph(A, labels=["a", "b"])


def test_agent_digraph_direction_weights_and_delays():
    s = scenario_from_dict({
        "social": {"A": [[0.5, 0.5], [0.2, 0.7]]},
        "agents": {"measure": [["1"], ["2"], ["1"]]},
        "network": {"weights": [[0.6, 0.4, 0.0], [0.0, 0.5, 0.5], [0.3, 0.0, 0.7]],
                    "delays": [[0, 2, 0], [0, 0, 1], [3, 0, 0]]}})
    g = agent_digraph(s)
    assert set(g.edges()) == {(2, 1), (3, 2), (1, 3)}       # agent 1 listens to agent 2
    assert g[2][1] == {"weight": 0.4, "delay": 2}
    assert g[1][3] == {"weight": 0.3, "delay": 3}
    assert nx.is_strongly_connected(g) == (len(agent_components(s.W)) == 1)


# -- python-control ---------------------------------------------------------------------------

def test_scalar_closed_loop_by_hand():
    control = _control()
    s = scenario_from_dict({"social": {"A": [[1.1]], "process_noise": 0.04},
                            "agents": {"measure": [["1"]], "measurement_noise": 0.09}})
    sys = closed_loop_ss(s, [np.array([[0.5]])])
    # e_{k+1} = (1 - 0.5) 1.1 e_k + 0.5 nu_k - 0.5 zeta_{k+1}
    assert np.allclose(sys.A, [[0.55]]) and np.allclose(sys.B, [[0.2 * 0.5, -0.3 * 0.5]])
    assert sys.isdtime() and sys.ninputs == 2 and sys.noutputs == 1
    variance = (0.04 * 0.25 + 0.09 * 0.25) / (1 - 0.55 ** 2)
    assert control.norm(sys, 2) ** 2 == pytest.approx(variance, rel=1e-12)
    assert closed_loop_for(s, [np.array([[0.5]])]).mse_steady(0.04, 0.09) == \
        pytest.approx(variance, rel=1e-12)


@pytest.mark.parametrize("spec", ["none", pytest.param("uniform:2", marks=pytest.mark.slow)])
def test_poles_and_h2_norm_are_the_exact_radius_and_mse(paper14, paper14_design, spec):
    control = _control()
    from design.gain_design import design_gains

    D = resolve_delays(paper14, spec)
    if np.array_equal(paper14_design.delays, D):       # paper-14's own delays: none
        G = paper14_design.G
    else:
        G = design_gains(paper14, delays=D, starts=1, max_iter=40).G
    sys = closed_loop_ss(paper14, G, D, dt=paper14.step_ms / 1000)
    loop = closed_loop_for(paper14, G, D)
    n, N = paper14.n, paper14.N
    assert sys.noutputs == n * N and sys.ninputs == n + N and sys.dt == 0.02
    assert sys.output_labels[0] == "e[1,1]" and sys.input_labels[-1] == "zeta[3,12]"
    assert np.max(np.abs(sys.poles())) == pytest.approx(loop.spectral_radius(), rel=1e-9)
    mse = loop.mse_steady(paper14.process_noise, paper14.measurement_noise)
    # the squared H2 norm as the energy of python-control's own impulse responses (every
    # input, 400 steps: rho^800 is negligible); control.norm(sys, 2) answers inf with
    # delays, as its Lyapunov solution has round-off negative eigenvalues where the
    # augmented state is unreachable
    per_step = control.ss(sys.A, sys.B, sys.C, sys.D, True)     # unit pulses, dt = 1 step
    pulses = control.impulse_response(per_step, T=np.arange(400))
    assert (pulses.outputs ** 2).sum() / (n * N) == pytest.approx(mse, rel=1e-8)
    if spec == "none":
        assert control.norm(sys, 2) ** 2 / (n * N) == pytest.approx(mse, rel=1e-8)
