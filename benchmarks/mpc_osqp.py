"""A linear MPC on osqp with the LQR's observer and model, for benchmarks/bench_tracking.py.

The same design as the LQR (falcon_plan.lqr): the observer, the feed-forward, the weights and
the delay line; instead of the gain, each tick solves a condensed QP over a horizon of
``HORIZON`` periods of the discrete model at the tick's sample (held over the horizon), with
the LQR's Riccati solution as the terminal cost and the device's speed-dependent limit as box
constraints on the commands. Unconstrained, it equals the LQR; it can only differ where the
limits bind. Not a production controller: a benchmark comparison.
"""
from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from falcon_plan.lqr import DelayModel, LqrTracker, LqrWeights, _dare

HORIZON = 10


class MpcTracker(LqrTracker):
    """:class:`LqrTracker` with the command from an osqp QP (module docstring)."""

    def __init__(self, schedule, limit: float, horizon: int = HORIZON, weights: LqrWeights = LqrWeights()) -> None:
        super().__init__(schedule, limit)
        self.horizon = horizon
        line = DelayModel.of(schedule.delay_samples).line
        self.q, self.r = weights.matrices(line)
        self.cache: dict[int, tuple] = {}
        self.nz = 6 + 3 * line

    def _qp(self, g: int):
        """The condensed QP of gain index g: (solver, F (nz, 3N))."""
        if g in self.cache:
            return self.cache[g]
        az, bz = self.s.systems[0][g], self.s.systems[1][g]
        n, nz = self.horizon, self.nz
        p_term = _dare(az, bz, self.q, self.r)
        phi = np.zeros(((n + 1) * nz, nz))
        gam = np.zeros(((n + 1) * nz, 3 * n))
        power = np.eye(nz)
        for i in range(n + 1):
            phi[i * nz:(i + 1) * nz] = power
            for j in range(i):
                gam[i * nz:(i + 1) * nz, 3 * j:3 * j + 3] = np.linalg.matrix_power(az, i - 1 - j) @ bz
            power = az @ power
        qbar = np.kron(np.eye(n + 1), self.q)
        qbar[n * nz:, n * nz:] = p_term
        h = gam.T @ qbar @ gam + np.kron(np.eye(n), self.r)
        f = phi.T @ qbar @ gam
        solver = osqp.OSQP()
        solver.setup(sp.csc_matrix(np.triu(h)), np.zeros(3 * n), sp.identity(3 * n, format="csc"),
                     -np.full(3 * n, 1e4), np.full(3 * n, 1e4), verbose=False, warm_starting=True,
                     eps_abs=1e-6, eps_rel=1e-6, polishing=False, max_iter=200)
        self.cache[g] = (solver, f)
        return self.cache[g]

    def _tick(self, k, y, held):
        if held is not None:
            return super()._tick(k, y, held)
        s, nx = self.s, self.nx
        kk = min(k, s.samples - 1)
        chi = self.xi.copy()
        if y is not None:
            chi[:9] += s.observer @ (y - chi[:3])
        d = chi[6:9]
        z0 = np.concatenate([chi[:6], (chi[9:nx].reshape(-1, 3) + d).ravel()])
        solver, f = self._qp(int(s.index[kk]))
        n = self.horizon
        idx = np.minimum(kk + np.arange(n), s.samples - 1)
        lim = self.limits[idx].ravel()
        uff = s.feedforward[idx].ravel()
        dd = np.tile(d, n)
        solver.update(q=f.T @ z0, l=-lim - uff + dd, u=lim - uff + dd)
        res = solver.solve()
        u_tilde = res.x[:3] if res.x is not None and np.all(np.isfinite(res.x[:3])) else np.zeros(3)
        uff0 = s.feedforward[kk]
        tc = np.clip(np.floor(uff0 + u_tilde - d + 0.5), -self.limits[kk], self.limits[kk])
        return super()._tick(k, y, tc)
