"""Scoring against the simulator's truth (benchmarks and the demo only; no fit imports this)."""

from __future__ import annotations

import numpy as np


def noise_floor(ds, dh_model, noise) -> float:
    """Expected held-out RMS from measurement noise alone, for this pose set and split.

    = sqrt(mean over held-out poses of [3 sigma_i^2 + trace(J_i Cov J_i^T)]) with sigma_i the
    simulator's per-axis sigma of a pose mean (systematic + averaged random parts) and Cov the
    covariance that noise alone gives the identifiable parameters on the training poses.
    """
    from workcell.kinematics.chain import jac_params

    train, test = ds.holdout_split(0.25)
    rng = np.linalg.norm(ds.p_tracker, axis=1)
    n_read = 5
    sig = np.array([noise.sigma_of_mean(r, n_read) for r in rng])
    th, base, free = dh_model.theta, dh_model.base_ref, dh_model.free
    Jt = np.asarray(jac_params(th, base, ds.q[train]))[:, :, free]
    Jh = np.asarray(jac_params(th, base, ds.q[test]))[:, :, free]
    W = 1.0 / sig[train] ** 2
    A = np.einsum("nkp,n,nkq->pq", Jt, W, Jt)
    cov = np.linalg.pinv(A)
    par = np.einsum("nkp,pq,nkq->n", Jh, cov, Jh)
    return float(np.sqrt(np.mean(3 * sig[test] ** 2 + par)))
