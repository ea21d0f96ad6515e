"""socmon's numerics: the model, its structure, the closed loop, estimation, experiments.

Pure functions of numpy/scipy/cvxpy data: no I/O, no zenoh, no logging side effects.
Never imports :mod:`agent` or :mod:`broker_free_net`.

Layers, lowest first. A module imports only from its own layer or the layers below it
(``tests/test_layers.py`` checks every import, lazy ones included):

1. **model** -- the objects of the paper and the graph algorithms they are checked with:
   :mod:`~design.errors`, :mod:`~design.files` (files read at a bounded cost),
   :mod:`~design.metrics`, :mod:`~design.noise`, :mod:`~design.plausibility` (the
   model's scale of the state, past which a value is refused),
   :mod:`~design.graph` (SCCs, condensation, parent SCCs), :mod:`~design.connectivity`
   (agent network), :mod:`~design.scenario`, :mod:`~design.gains`,
   :mod:`~design.generate` (generated scenarios).
2. **structure** -- what the structure implies: :mod:`~design.observability`
   (staircase, distributed detectability), :mod:`~design.recovery`,
   :mod:`~design.analysis`.
3. **loop** -- the estimator and its exact closed loop: :mod:`~design.estimator`,
   :mod:`~design.closed_loop`, :mod:`~design.structured` (the loop applied through its
   sparse and low-rank factors), :mod:`~design.certificates`, :mod:`~design.gap` (the
   loop between a failure and the switch), :mod:`~design.residuals` (residual tests
   with exact thresholds from the loop's covariance, and fault isolation).
4. **estimation** -- gains and Monte-Carlo runs: :mod:`~design.ccl`,
   :mod:`~design.gradient`, :mod:`~design.gain_design`, :mod:`~design.simulate`.
5. **experiments** -- pipelines over all of the above: :mod:`~design.experiments`,
   :mod:`~design.reconfigure`, :mod:`~design.simulation_report` (a Monte-Carlo run beside
   the exact figures of its loop), :mod:`~design.reports` (the records of ``analyze``,
   ``certify``, ``plan`` and ``design``), and :mod:`~design.interop` (python-control,
   networkx).

Heavy imports (cvxpy) happen inside the functions that need them.
"""

#: Layer of every module of the package (checked by tests/test_layers.py).
LAYERS = {
    "errors": 1, "files": 1, "metrics": 1, "noise": 1, "plausibility": 1, "graph": 1,
    "connectivity": 1, "scenario": 1, "gains": 1, "generate": 1,
    "observability": 2, "recovery": 2, "analysis": 2, "roster": 2,
    "estimator": 3, "closed_loop": 3, "structured": 3, "certificates": 3, "gap": 3,
    "residuals": 3,
    "ccl": 4, "gradient": 4, "gain_design": 4, "simulate": 4,
    "reconfigure": 5, "experiments": 5, "interop": 5, "simulation_report": 5,
    "reports": 5,
}
