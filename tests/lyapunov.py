"""The Lyapunov functions of the thesis's analyses, evaluated along a simulation log."""

from __future__ import annotations

import numpy as np


def _batch(f, q):
    n = q.shape[1]
    return np.array(f.map(len(q))(q.T)).reshape(-1, len(q), n).transpose(1, 0, 2)


def derivative_misfits(result, skip_s: float = 0.2):
    """RMS misfit of dV/dt along the log against the analysis without / with the cross term.

    With the scenario's weight K of the position error (ones in the thesis):
    g (3.39): V = e_g'K e_g/2 + e_v'M e_v/2 + p~'p~/2, dV/dt = -e_g'K G_g e_g - e_v'G_a e_v
    [+ e_g'K J e_v, the term the thesis's (3.40) drops].
    e, f (3.12, 3.60): V = e'K e/2 + r'M r/2 + p~'p~/2, dV/dt = -e'K alpha e - r'G r
    [+ e'K r, left when the law has no known term K e].
    The plant must be nominal (p~ = p_nominal - p^) and Gamma = 1. The first ``skip_s``
    seconds are left out: there, sampling effects of the large initial errors dominate.
    """
    u = result.units[0]
    m, h = u.setup.controller_model, result.scenario.period
    n, nd = m.nq, u.setup.controller.n_desired
    M = _batch(m.M, u.q)
    first, second = u.errors[:, :nd], u.errors[:, nd:]
    g1, g2, weight = u.setup.gains[:nd], u.setup.gains[nd:nd + n], u.setup.gains[nd + n:]
    V = (0.5 * (weight * first ** 2).sum(1) + 0.5 * np.einsum("ki,kij,kj->k", second, M, second)
         + 0.5 * ((m.p_nominal - u.p_hat) ** 2).sum(1))
    analysed = -(weight * g1 * first ** 2).sum(1) - (g2 * second ** 2).sum(1)
    if u.setup.controller.kind == "g":
        cross = np.einsum("ki,kij,kj->k", weight * first, _batch(m.J_world, u.q), second)
    else:
        cross = (weight * first * second).sum(1)
    dV = (V[2:] - V[:-2]) / (2 * h)
    window = slice(int(round(skip_s / h)), None)
    rms = lambda x: float(np.sqrt(np.mean(x[window] ** 2)))  # noqa: E731
    return rms(dV - analysed[1:-1]), rms(dV - analysed[1:-1] - cross[1:-1])
