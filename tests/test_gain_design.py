"""Gain design: the paper's LMI algorithm (ccl) and the default on the exact delayed loop."""

import numpy as np
import pytest

from design.ccl import CCLProblem, SolverError, ccl_design
from design.closed_loop import ClosedLoop, delay_free_matrix
from design.errors import NotObservableError, ScenarioError
from design.gain_design import DesignError, blas_threads, check_detectable, design_gains
from design.gains import gains_meta, load_gains, save_gains
from design.gradient import LoopModel
from design.scenario import resolve_delays, scenario_from_dict


def _tiny(A, measure, W=None):
    A = np.asarray(A, dtype=float)
    data = {
        "name": "tiny",
        "social": {"A": A.tolist()},
        "agents": {"measure": measure},
        "network": {"topology": "cycle", "self_weight": 0.5} if W is None else {"weights": W},
    }
    return scenario_from_dict(data)


@pytest.fixture(scope="module")
def ccl_paper14(paper14):
    # SCS: the same LMIs solve in ~1 s instead of ~25 s with CLARABEL (see docs/gain-design.md)
    return design_gains(paper14, delays="none", method="ccl", solver="SCS")


# -- the LMIs ------------------------------------------------------------------------


def test_lmi_blocks_equal_np_block(paper14):
    s = paper14
    lmi = CCLProblem(s.A, s.W, s.measure)
    rng = np.random.default_rng(3)
    G = [rng.normal(size=(s.n, len(m))) for m in s.measure]
    m = s.n * s.N
    Q = rng.normal(size=(m, m)); Q = Q + Q.T
    R = rng.normal(size=(m, m)); R = R + R.T
    for var, val in zip(lmi.G, G):
        var.value = val
    lmi.Q.value, lmi.R.value = Q, R
    Ahat = delay_free_matrix(s.A, s.W, s.measure, G)
    np.testing.assert_allclose(lmi.Ahat.value, Ahat, atol=1e-12)
    np.testing.assert_allclose(lmi.lmi_closed_loop.value, np.block([[Q, Ahat.T], [Ahat, R]]),
                               atol=1e-12)
    np.testing.assert_allclose(lmi.lmi_coupling.value,
                               np.block([[Q, np.eye(m)], [np.eye(m), R]]), atol=1e-12)
    # the closed loop of the LMI is (I - K D_H)(W (x) A) with K = blockdiag(K^i), K^i H_i^T = G_i
    K = np.zeros((m, m))
    for i, mi in enumerate(s.measure):
        for c, v in enumerate(mi):
            K[i * s.n:(i + 1) * s.n, i * s.n + v] = G[i][:, c]
    np.testing.assert_allclose(Ahat, (np.eye(m) - K @ s.D_H) @ np.kron(s.W, s.A), atol=1e-12)


def test_ccl_paper14_reaches_rho_below_one(ccl_paper14):
    res = ccl_paper14
    assert res.method == "ccl" and res.stable and res.rho < 1
    assert res.status == "rho(Ahat) < 1"
    assert [h["status"] for h in res.history] == ["optimal"] * len(res.history)
    assert res.history[0]["solve"] == "initial feasibility solve"
    # the recorded radius of the last solve is the one of the gain returned
    assert res.history[-1]["rho_delay_free"] == pytest.approx(res.rho, abs=1e-9)


def test_ccl_default_solver_is_clarabel_on_a_tiny_problem():
    s = _tiny([[1.2, 0.3], [0.0, 0.9]], [["1"], ["1"]])
    res = design_gains(s, delays="none", method="ccl", keep_iterating=True, max_iter=5)
    assert res.options["solver"] == "CLARABEL"
    assert res.stable and res.rho < 1


@pytest.mark.filterwarnings("ignore:Solution may be inaccurate")
def test_ccl_inaccurate_solve_raises_solver_error(paper14):
    with pytest.raises(SolverError, match="initial feasibility solve: solver SCS returned "
                                          "status 'optimal_inaccurate'") as info:
        design_gains(paper14, method="ccl", solver="SCS", solver_options={"max_iters": 5})
    assert info.value.history[-1]["status"] == "optimal_inaccurate"


def test_ccl_without_a_stabilising_gain_is_not_stable():
    # node 1 (unstable) is never seen: the LMIs stay feasible (Q, R large) but the
    # cone-complementarity iteration cannot bring rho(Ahat) below 1
    A = np.array([[1.5, 0.0], [0.0, 0.5]])
    out = ccl_design(A, np.array([[1.0]]), [(1,)], max_iter=3)
    assert out["rho_delay_free"] >= 1.5 - 1e-9 and out["reason"] == "max iterations"


def test_delay_free_design_is_reported_unstable_at_uniform7(paper14, ccl_paper14):
    G = ccl_paper14.G
    D7 = resolve_delays(paper14, "uniform:7")
    assert ClosedLoop(paper14.A, paper14.W, D7, paper14.measure, G).spectral_radius() > 1
    res = design_gains(paper14, delays="uniform:7", method="ccl", solver="SCS")
    assert res.rho_delay_free < 1
    assert not res.stable and res.rho > 1 and res.mse_steady is None
    np.testing.assert_array_equal(res.delays, D7)


# -- the default method --------------------------------------------------------------


@pytest.mark.parametrize("spec", ["none", "uniform:3", "uniform:7",
                                  pytest.param("uniform:15", marks=pytest.mark.slow)])
def test_default_stabilises_paper14_with_delays(paper14, spec, tmp_path):
    opts = {"starts": 1, "max_iter": 60, "target": 0.995, "gaps": False}
    res = design_gains(paper14, delays=spec, **opts)
    assert res.stable and res.rho < 0.995
    D = resolve_delays(paper14, spec)
    np.testing.assert_array_equal(res.delays, D)
    path = tmp_path / "g.npz"
    save_gains(path, res.G, gains_meta(paper14, res.method, res.delays, res.rho))
    loaded = load_gains(path, paper14)
    rho = ClosedLoop(paper14.A, paper14.W, D, paper14.measure, loaded.G).spectral_radius()
    assert rho == pytest.approx(res.rho, abs=1e-12) and rho < 1


def test_default_beats_ccl_radius_delay_free(paper14, ccl_paper14):
    # the nominal radius alone (the gap terms trade some of it: test_gap.py)
    res = design_gains(paper14, delays="none", starts=1, max_iter=50, gaps=False)
    assert res.rho < ccl_paper14.rho - 0.2


@pytest.mark.slow
def test_mse_objective_lowers_the_steady_error(paper14):
    by_rho = design_gains(paper14, delays="none", starts=1, max_iter=40)
    by_mse = design_gains(paper14, delays="none", objective="mse", starts=1, max_iter=60)
    assert by_mse.stable and by_mse.rho < 1
    assert by_mse.mse_steady < 0.7 * by_rho.mse_steady
    loop = ClosedLoop(paper14.A, paper14.W, by_mse.delays, paper14.measure, by_mse.G)
    assert by_mse.mse_steady == pytest.approx(
        loop.mse_steady(paper14.process_noise, paper14.measurement_noise), rel=1e-12)


@pytest.mark.slow
def test_design_is_deterministic_for_a_seed(paper14):
    a = design_gains(paper14, delays="uniform:2", seed=5, starts=2, max_iter=15)
    b = design_gains(paper14, delays="uniform:2", seed=5, starts=2, max_iter=15)
    for ga, gb in zip(a.G, b.G):
        np.testing.assert_array_equal(ga, gb)
    assert a.rho == b.rho


# -- gradients against finite differences ---------------------------------------------


def _fd(f, x, h=1e-6):
    with blas_threads(1):
        return np.array([(f(x + h * e) - f(x - h * e)) / (2 * h) for e in np.eye(x.size)])


@pytest.mark.parametrize("tau", [0, 2])
def test_radius_gradient_matches_finite_differences(paper14, tau):
    s = paper14
    model = LoopModel(s.A, s.W, resolve_delays(s, f"uniform:{tau}"), s.measure)
    x = 0.3 * np.random.default_rng(tau).normal(size=model.size)
    value, grad = model.spectral_radius_and_gradient(x)
    assert value == pytest.approx(model.spectral_radius(x), rel=1e-10)
    fd = _fd(lambda z: model.spectral_radius_and_gradient(z)[0], x)
    np.testing.assert_allclose(grad, fd, atol=1e-6 * max(1.0, np.abs(fd).max()))


@pytest.mark.parametrize("tau", [0, pytest.param(2, marks=pytest.mark.slow)])
def test_mse_gradient_matches_finite_differences(paper14, tau):
    s = paper14
    D = resolve_delays(s, f"uniform:{tau}")
    G = design_gains(s, delays=D, starts=1, max_iter=10).G        # a stable point
    model = LoopModel(s.A, s.W, D, s.measure)
    x = model.pack(G) + 0.01 * np.random.default_rng(7).normal(size=model.size)
    q, r = s.process_noise, s.measurement_noise
    J, grad = model.mse_and_gradient(x, q, r)
    assert J == pytest.approx(ClosedLoop(s.A, s.W, D, s.measure, model.unpack(x)).mse_steady(q, r),
                              rel=1e-10)
    fd = _fd(lambda z: model.mse_and_gradient(z, q, r)[0], x)
    np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6 * np.abs(fd).max())


def test_mse_of_an_unstable_gain_is_infinite(paper14):
    model = LoopModel(paper14.A, paper14.W, paper14.delays, paper14.measure)
    J, g = model.mse_and_gradient(np.zeros(model.size), 0.05, 0.05)
    assert J == np.inf and g is None


# -- preconditions ---------------------------------------------------------------------


def test_paper14_pair_is_detectable_not_observable(paper14):
    d = check_detectable(paper14)
    assert (d.rank, d.order, d.observable, d.detectable) == (33, 42, False, True)
    assert max(abs(z) for z in d.unobservable_modes) == pytest.approx(0.2263, abs=1e-4)


def test_unmeasured_parent_scc_is_named(paper14):
    s = paper14.replace(measure=((6,), (8,), (9,)))      # nodes 7, 9, 10: {12,13,14} unseen
    with pytest.raises(NotObservableError, match=r"\{12, 13, 14\} has no sensor") as info:
        design_gains(s)
    assert info.value.unmeasured == [["12", "13", "14"]]


def test_unmeasured_unstable_singleton_parent_is_named():
    # node 2 (unstable) neither influences nor is influenced by node 1: its own parent SCC
    s = _tiny([[0.5, 0.0], [0.0, 1.3]], [["1"], ["1"]])
    with pytest.raises(NotObservableError, match=r"\{2\} has no sensor"):
        design_gains(s)


def test_bad_arguments_are_named(paper14):
    with pytest.raises(DesignError, match="method"):
        design_gains(paper14, method="lqr")
    with pytest.raises(DesignError, match="objective"):
        design_gains(paper14, objective="h2")
    with pytest.raises(DesignError, match="ccl designs for stability"):
        design_gains(paper14, method="ccl", objective="mse")
    with pytest.raises(DesignError, match=r"\['solver'\]"):
        design_gains(paper14, solver="SCS")
    with pytest.raises(DesignError, match="3 x 3 integer"):
        design_gains(paper14, delays=np.zeros((2, 2), int))
    with pytest.raises(ScenarioError, match="not a link"):
        design_gains(paper14, delays=np.array([[0, 1, 1], [0, 0, 1], [1, 0, 0]]))
    with pytest.raises(ValueError, match="solver"):
        design_gains(paper14, method="ccl", solver="MOSEK")


# -- warm starts, progress, the structured MSE ----------------------------------------


@pytest.mark.slow
def test_warm_start_from_a_neighbouring_design_is_certified_stable(paper14):
    # the gain for 2-step delays starts the design for 3-step delays: one start
    s = paper14
    G2 = design_gains(s, delays="uniform:2", starts=1, max_iter=30).G
    res = design_gains(s, delays="uniform:3", objective="mse", init=G2, max_iter=30)
    assert [h["stage"] for h in res.history if h["stage"].endswith("done")] == ["start 0 done"]
    D = resolve_delays(s, "uniform:3")
    loop = ClosedLoop(s.A, s.W, D, s.measure, res.G)
    assert res.stable and res.rho == pytest.approx(loop.spectral_radius(), abs=1e-12)
    assert res.rho < 1
    assert res.mse_steady == pytest.approx(loop.mse_steady(s.process_noise,
                                                           s.measurement_noise), rel=1e-12)
    # from the delay-free design: also one start, also certified
    res0 = design_gains(s, delays="uniform:3", objective="rho", init="delay-free",
                        max_iter=20, target=0.95)
    assert res0.stable and res0.rho < 0.95
    assert res0.rho == pytest.approx(ClosedLoop(s.A, s.W, D, s.measure, res0.G)
                                     .spectral_radius(), abs=1e-12)


@pytest.mark.slow
def test_progress_callback_reports_every_iteration(paper14):
    seen = []
    res = design_gains(paper14, delays="uniform:2", objective="mse", max_iter=25,
                       time_limit=600, progress=seen.append, gaps=False)
    stages = [p.stage for p in seen]
    assert stages[0] == "start 1 of 1, radius" and stages[-2] == "start 1 of 1, MSE"
    assert stages[-1].startswith("certifying") and np.isnan(seen[-1].value)
    seen.pop()
    assert {p.quantity for p in seen} == {"rho", "mse"}
    # one report per iteration of each stage (iteration 0 is the stage's start)
    mse = [p for p in seen if p.quantity == "mse"]
    assert [p.iteration for p in mse] == list(range(len(mse)))
    assert seen[-1].iterations == res.iterations
    assert all(b.elapsed >= a.elapsed for a, b in zip(seen, seen[1:]))
    assert all(p.time_left is not None and 0 <= p.time_left <= 600 for p in seen)
    # the last MSE reported is the certified steady MSE of the result
    assert mse[-1].value == pytest.approx(res.mse_steady, rel=1e-9)
    # with the gap terms (a gap of this gain is above the target), their rounds follow,
    # reporting the worst gap radius
    seen.clear()
    res = design_gains(paper14, delays="uniform:2", objective="mse", max_iter=25,
                       progress=seen.append)
    assert res.gap_design["iterations"] > 0
    gap = [p for p in seen if p.stage.startswith("gap loops")]
    assert gap and {p.quantity for p in gap} == {"rho"} and gap[0].stage.endswith("round 1")
    assert seen[-1].iterations == res.iterations
    # the default design's own starts: three for the radius, with the best so far
    seen.clear()
    design_gains(paper14, delays="none", max_iter=5, progress=seen.append, gaps=False)
    assert {p.stage for p in seen[:-1]} == {f"start {k} of 3, radius" for k in (1, 2, 3)}
    assert seen[0].best is None and seen[-1].best is not None


@pytest.mark.parametrize("delays", [[[0, 2], [1, 0]], [[0, 3], [0, 0]], [[0, 0], [0, 0]]])
def test_structured_mse_equals_the_dense_lyapunov_one(delays):
    # small cases with unequal delays: the impulse-response MSE and its gradient against
    # two dense Lyapunov solves of the augmented loop
    s = _tiny([[1.05, 0.3, 0.0], [0.0, 0.6, 0.4], [0.5, 0.0, 0.7]], [["1"], ["3"]],
              W=[[0.6, 0.4], [0.3, 0.7]])
    D = np.array(delays)
    model = LoopModel(s.A, s.W, D, s.measure)
    rng = np.random.default_rng(7)
    q, r = 0.3, 0.2
    for _ in range(3):
        x = 0.5 + 0.2 * rng.standard_normal(model.size)
        if not ClosedLoop(s.A, s.W, D, s.measure, model.unpack(x)).spectral_radius() < 0.98:
            continue
        J, g, _ = model.mse_impulse(x, q, r)
        J_ref, g_ref = model.mse_and_gradient(x, q, r, method="lyapunov")
        exact = ClosedLoop(s.A, s.W, D, s.measure, model.unpack(x)).mse_steady(q, r)
        assert abs(J - exact) <= 1e-9 * exact and abs(J - J_ref) <= 1e-9 * J_ref
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-9 * max(1.0, np.abs(g_ref).max()))
        break
    else:
        pytest.fail("no stable sample gain")


@pytest.mark.slow
def test_a_design_through_arpack_is_the_same_run_after_run(paper14):
    """Above DENSE_SPECTRUM_MAX_ORDER the radius comes from ARPACK, whose own start is
    random: the design starts it from a fixed vector, so one call gives one gain."""
    from design.gain_design import design_gains

    runs = [design_gains(paper14, delays="uniform:10", objective="rho", max_iter=8,
                         starts=1, gaps=False, report_gaps=False, time_limit=None)
            for _ in range(2)]
    assert runs[0].iterations == runs[1].iterations > 0
    for a, b in zip(runs[0].G, runs[1].G):
        np.testing.assert_array_equal(a, b)
