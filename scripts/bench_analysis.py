"""Benchmark: structural analysis of a 1,000,000-edge digraph; paper-14 certificate at tau 15.

Run from the project root:

    python scripts/bench_analysis.py                 # default sizes, networkx baseline on
    python scripts/bench_analysis.py --edges 200000 --no-baseline

1. A random directed graph (``--nodes`` nodes, ``--edges`` edges drawn uniformly with
   numpy, seed ``--seed``) as a scipy.sparse A; times :func:`design.analysis.structural_analysis`
   (SCCs + condensation + parent SCCs + minimal sensor set), best of ``--repeat`` runs,
   and, as the baseline in the same run, networkx's SCCs + condensation on the same graph.
2. paper-14 with a gain from :func:`radius_descent_gain` (a documented simple method,
   below); times the certificate pieces at taubar = 15: the exact radius of the delayed
   loop (companion of order 16 nN = 672), the Theorem 1 criterion, the paper formula,
   and the full ``certify`` call for taus 0, 3, 7, 15.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from design.closed_loop import ClosedLoop  # noqa: E402


def radius_descent_gain(scenario, steps: int = 300, lr: float = 0.05):
    """A stabilising gain by plain gradient descent on the delay-free spectral radius.

    Starts from G = 0 and follows the eigenvalue sensitivity of the largest-modulus
    eigenvalue of ``Ahat = (I - K D_H)(W (x) A)``: with right/left eigenvectors v, u,
    ``d|lambda| = Re(conj(lambda)/|lambda| * u^T dAhat v / (u^T v))`` and
    ``dAhat`` (block row i) ``= -dG_i H_i (W (x) A)_i``. Fixed step ``lr``, ``steps``
    iterations, keeps the best iterate. Not an optimal design (that is the gain-design
    command's job); on paper-14 it reaches rho(Ahat) ~ 0.78 in 300 steps.

    Returns
    -------
    (rho, G) : float, list of (n, p_i) arrays
    """
    n, N = scenario.n, scenario.N
    zero = np.zeros_like(scenario.delays)
    WA = np.kron(scenario.W, scenario.A)
    G = [np.zeros((n, len(m))) for m in scenario.measure]
    best_rho, best_G = np.inf, None
    for _ in range(steps):
        M = ClosedLoop(scenario.A, scenario.W, zero, scenario.measure, G).F(0)
        lam, V = np.linalg.eig(M)
        i = int(np.argmax(np.abs(lam)))
        rho = float(abs(lam[i]))
        if rho < best_rho:
            best_rho, best_G = rho, [g.copy() for g in G]
        lamL, U = np.linalg.eig(M.T)
        u = U[:, int(np.argmin(np.abs(lamL - lam[i])))]
        v = V[:, i]
        c = np.conj(lam[i]) / max(rho, 1e-300) / (u @ v)
        for a in range(N):
            rows = slice(a * n, (a + 1) * n)
            HR = WA[rows][list(scenario.measure[a])]
            grad = -np.real(c * np.outer(u[rows], HR @ v))
            G[a] = G[a] - lr * grad
    return best_rho, best_G


def _best(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def bench_structure(nodes, edges, seed, repeat, baseline):
    import scipy.sparse as sp

    from design.analysis import structural_analysis

    rng = np.random.default_rng(seed)
    # exactly `edges` distinct off-diagonal pairs (draw a few more, drop loops/duplicates)
    keys = np.empty(0, dtype=np.int64)
    while keys.size < edges:
        extra = rng.integers(0, nodes * nodes, int(1.05 * edges) + 10, dtype=np.int64)
        keys = np.unique(np.concatenate([keys, extra[extra // nodes != extra % nodes]]))
    keys = rng.permutation(keys)[:edges]
    rows, cols = keys // nodes, keys % nodes
    A = sp.csr_matrix((rng.uniform(0.1, 1.0, edges), (rows, cols)), shape=(nodes, nodes))
    measured = rng.choice(nodes, size=min(1000, nodes), replace=False)
    t, s = _best(lambda: structural_analysis(A, measured), repeat)
    print(f"[structure] random digraph: {nodes} nodes, {s.n_edges} edges (seed {seed})")
    print(f"  structural_analysis (SCCs + condensation + parents + minimal sensor set): "
          f"{t:.3f} s (best of {repeat})")
    print(f"  -> {s.n_sccs} SCCs, {len(s.parents)} parent SCCs, {s.condensation_edges} "
          f"condensation edges, largest SCC {int(s.structure.components.sizes().max())} nodes, "
          f"{len(s.unmeasured_parents)} parents unmeasured, minimal sensor set "
          f"{len(s.minimal_sensor_set)} nodes")
    if baseline:
        import networkx as nx

        G = nx.DiGraph()
        G.add_nodes_from(range(nodes))
        G.add_edges_from(zip(cols.tolist(), rows.tolist()))
        t0 = time.perf_counter()
        C = nx.condensation(G)
        sinks = sum(1 for c in C if C.out_degree(c) == 0)
        tb = time.perf_counter() - t0
        print(f"  baseline networkx condensation + sinks on the same graph: {tb:.3f} s "
              f"({C.number_of_nodes()} SCCs, {sinks} sinks): {tb / t:.0f}x slower")
        assert C.number_of_nodes() == s.n_sccs and sinks == len(s.parents)


def bench_certificate(repeat):
    from design.certificates import certify, paper_formula, theorem1_radius
    from design.closed_loop import spectral_radius
    from design.scenario import load_scenario, uniform_delays

    s = load_scenario("paper-14")
    t0 = time.perf_counter()
    rho, G = radius_descent_gain(s)
    tg = time.perf_counter() - t0
    print(f"[certificate] paper-14, gain by radius descent (300 steps, {tg:.2f} s): "
          f"rho(Ahat) = {rho:.4f}")
    tau = 15
    loop = ClosedLoop(s.A, s.W, uniform_delays(s.W, tau), s.measure, G)
    t_exact, r_exact = _best(lambda: ClosedLoop(s.A, s.W, uniform_delays(s.W, tau), s.measure,
                                                G).spectral_radius(), repeat)
    t_t1, r_t1 = _best(lambda: theorem1_radius(s.A, s.W, s.measure, G, tau), repeat)
    t_pf, r_pf = _best(lambda: paper_formula(
        spectral_radius(ClosedLoop(s.A, s.W, np.zeros((3, 3), int), s.measure, G).F(0)), tau),
        repeat)
    print(f"  taubar = 15: exact radius {r_exact:.6f} (companion order {loop.order}): "
          f"{t_exact:.3f} s; Theorem 1 radius {r_t1:.4g}: {t_t1 * 1e3:.1f} ms; "
          f"paper formula {r_pf:.6f}: {t_pf * 1e3:.1f} ms (best of {repeat})")
    print(f"  sum for taubar = 15 (exact + Theorem 1 + formula): {t_exact + t_t1 + t_pf:.3f} s")
    t_all, c = _best(lambda: certify(s, G, taus=[0, 3, 7, 15]), 1)
    print(f"  full certify (taus 0,3,7,15, tau_star search, exact MSE, Phi): {t_all:.3f} s; "
          f"tau_star = {c['tau_star']}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--nodes", type=int, default=200_000)
    p.add_argument("--edges", type=int, default=1_000_000)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--repeat", type=int, default=3)
    p.add_argument("--no-baseline", action="store_true", help="skip the networkx baseline")
    args = p.parse_args(argv)
    import os
    import platform

    print(f"python {platform.python_version()}, numpy {np.__version__}, "
          f"{os.cpu_count()} cpus, load average {os.getloadavg()[0]:.2f}")
    bench_structure(args.nodes, args.edges, args.seed, args.repeat, not args.no_baseline)
    bench_certificate(args.repeat)


if __name__ == "__main__":
    main()
