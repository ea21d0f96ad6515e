"""The world's state machine: the social system advanced one step at a time, no socket.

The process shell (:mod:`agent.world.process`) publishes its truth and the agents' sensor
readings; the simulated runtime (:mod:`agent.run.simulated`) steps it by hand.
"""

from __future__ import annotations

import math

import numpy as np

from design import noise

__all__ = ["WorldCore", "resolution_step"]

class WorldCore:
    """The social system ``x_{k+1} = A x_k + nu_k`` with the noise of :mod:`design.noise`.

    Examples
    --------
    >>> import numpy as np
    >>> w = WorldCore(np.eye(2), seed=3, q=0.0)
    >>> x0 = w.x.copy(); w.advance(); w.step, bool((w.x == x0).all())
    (1, True)
    """

    def __init__(self, A, seed: int, q: float):
        self.A = np.asarray(A, dtype=float)
        self.n = self.A.shape[0]
        self.seed = int(seed)
        self.q = float(q)
        self.step = 0
        self.x = noise.initial_state(self.seed, self.n)[0]
        self._process_noise = noise.StepDraws(
            lambda k, n: noise.process_noise(self.seed, k, n, self.q)[0])

    def advance(self) -> None:
        """Go from step k to k + 1."""
        nu = self._process_noise(self.step, self.n)
        self.x = self.A @ self.x + nu
        self.step += 1


def resolution_step(rho: float, x0_norm: float, digits: float = 6.0):
    """First step at which an O(1) error keeps fewer than ``digits`` significant digits.

    With ``|x_k| ~ |x_0| rho^k``, float64 resolves ``|x_k| * eps``; an error of 1 keeps
    ``-log10(|x_k| eps)`` digits. None when rho <= 1 (the state does not grow).

    >>> resolution_step(1.0857, 1.0, digits=0)   # |x| * eps reaches 1
    439
    >>> resolution_step(0.98, 1.0) is None
    True
    """
    if rho <= 1.0:
        return None
    eps = np.finfo(float).eps
    limit = 10.0 ** (-digits) / eps / max(x0_norm, 1e-300)
    return max(0, math.ceil(math.log(limit) / math.log(rho)))
