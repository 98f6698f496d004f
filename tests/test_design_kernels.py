"""Geometry-aware kernels and GP-UCB on S3 x R3 (seed 002, Das, Touma & Burdick)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workcell.estimation.design import (
    GPHyperparameters,
    PoseGP,
    heat_kernel_num_terms,
    heat_kernel_truncation_bound,
    naive_geodesic_kernel,
    naive_se3_kernel,
    pose_error_objective,
    pose_product_kernel,
    quaternion_geodesic_distance,
    s3_heat_kernel,
    select_next_pose,
    srinivas_beta,
)
from workcell.estimation.design.kernels import heat_series

# --------------------------------------------------------------------------- helpers


def random_quats(rng: np.random.Generator, n: int) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_poses(rng: np.random.Generator, n: int, half_width_m: float = 0.5) -> np.ndarray:
    return np.hstack([random_quats(rng, n), rng.uniform(-half_width_m, half_width_m, (n, 3))])


def awkward_pose_set(rng: np.random.Generator, n: int) -> np.ndarray:
    """Random poses plus exact duplicates, antipodal copies (q -> -q) and near-duplicates."""
    base = random_poses(rng, n)
    dup = base[: max(1, n // 5)].copy()
    anti = base[: max(1, n // 5)].copy()
    anti[:, :4] *= -1.0
    near = base[: max(1, n // 5)].copy()
    near[:, :4] += 1e-4 * rng.normal(size=(near.shape[0], 4))
    near[:, :4] /= np.linalg.norm(near[:, :4], axis=1, keepdims=True)
    near[:, 4:] += 1e-4 * rng.normal(size=(near.shape[0], 3))
    return np.vstack([base, dup, anti, near])


# Example 1 of the paper: four identical positions, four unit quaternions (wxyz).
S = 1.0 / math.sqrt(2.0)
EXAMPLE1_QUATS = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [S, S, 0, 0], [S, 0, S, 0]], dtype=float)
EXAMPLE1_POSES = np.hstack([EXAMPLE1_QUATS, np.zeros((4, 3))])


# ------------------------------------------------------------------ validity (PSD)


@pytest.mark.parametrize("variant", ["so3", "s3", "paper"])
def test_product_kernel_gram_is_psd_on_random_pose_sets(variant: str) -> None:
    rng = np.random.default_rng(20240917)
    worst = np.inf
    for _ in range(40):
        poses = awkward_pose_set(rng, int(rng.integers(4, 40)))
        kappa = float(np.exp(rng.uniform(math.log(0.05), math.log(3.0))))
        ell = float(np.exp(rng.uniform(math.log(0.01), math.log(2.0))))
        variance = float(np.exp(rng.uniform(-3.0, 3.0)))
        k = pose_product_kernel(
            poses, poses, kappa=kappa, lengthscale_m=ell, variance=variance, variant=variant
        )
        assert np.allclose(k, k.T, atol=1e-14 * variance)
        eig_min = np.linalg.eigvalsh(k)[0]
        scale = np.trace(k)
        worst = min(worst, eig_min / scale)
        assert eig_min >= -1e-10 * scale, (variant, kappa, ell, eig_min, scale)
    assert np.isfinite(worst)


def test_product_kernel_unit_diagonal_and_antipodal_invariance() -> None:
    rng = np.random.default_rng(3)
    a = random_poses(rng, 12)
    b = random_poses(rng, 9)
    b_flipped = b.copy()
    b_flipped[:, :4] *= -1.0
    for variant in ("so3", "paper"):
        k = pose_product_kernel(a, b, kappa=0.4, lengthscale_m=0.2, variance=2.5, variant=variant)
        k_flip = pose_product_kernel(
            a, b_flipped, kappa=0.4, lengthscale_m=0.2, variance=2.5, variant=variant
        )
        assert k.shape == (12, 9)
        np.testing.assert_allclose(k, k_flip, rtol=0, atol=1e-13)
        diag = np.diag(
            pose_product_kernel(a, a, kappa=0.4, lengthscale_m=0.2, variance=2.5, variant=variant)
        )
        np.testing.assert_allclose(diag, 2.5, rtol=1e-12)
    # Without identification, q and -q are the farthest points of S3.
    k_s3 = s3_heat_kernel(a[:1, :4], -a[:1, :4], 0.4, variant="s3")
    assert k_s3[0, 0] < 1e-3


def test_example1_points_product_heat_kernel_is_positive_definite() -> None:
    for kappa in (0.1, 0.5, 1.0, 2.0):
        k = pose_product_kernel(EXAMPLE1_POSES, EXAMPLE1_POSES, kappa=kappa, lengthscale_m=1.0)
        assert np.linalg.eigvalsh(k)[0] > 0.0
    # Very wide kernel (as wide as the naive beta = 12 one): numerically rank one, never < 0.
    k = pose_product_kernel(EXAMPLE1_POSES, EXAMPLE1_POSES, kappa=12.0, lengthscale_m=1.0)
    assert np.linalg.eigvalsh(k)[0] >= -1e-12 * np.trace(k)


# ----------------------------------------------------------- naive kernel (Example 1)


def test_naive_geodesic_kernel_is_not_pd_on_paper_example1() -> None:
    # beta = 12, gamma1 = 0.1, gamma2 = 0.9: the paper reports eig(K) =
    # (-0.0001, 0.0083, 0.0355, 3.9561) (digits truncated, not rounded).
    k = naive_se3_kernel(EXAMPLE1_POSES, EXAMPLE1_POSES, beta=12.0, gamma_pos=0.1, gamma_rot=0.9)
    eig = np.linalg.eigvalsh(k)
    np.testing.assert_allclose(eig, [-0.0001, 0.0083, 0.0355, 3.9561], atol=1e-4)
    # Negative by ~1e-4 on a matrix of norm ~4: eleven orders above round-off.
    assert eig[0] < -5e-5
    # Same matrix from the pure-rotation naive kernel with l = beta / gamma2.
    k_rot = naive_geodesic_kernel(EXAMPLE1_QUATS, EXAMPLE1_QUATS, 12.0 / 0.9)
    np.testing.assert_allclose(k_rot, k, rtol=1e-14)
    # beta = 1: the paper reports (0.4725, 0.6940, 1.1404, 1.6929), PD for this set.
    eig1 = np.linalg.eigvalsh(naive_se3_kernel(EXAMPLE1_POSES, EXAMPLE1_POSES, beta=1.0))
    np.testing.assert_allclose(eig1, [0.4725, 0.6940, 1.1404, 1.6929], atol=1e-4)
    assert eig1[0] > 0.0


def test_geodesic_distance_matches_eq1() -> None:
    d = quaternion_geodesic_distance(EXAMPLE1_QUATS, EXAMPLE1_QUATS)
    expected = np.array(
        [
            [0, math.pi, math.pi / 2, math.pi / 2],
            [math.pi, 0, math.pi / 2, math.pi],
            [math.pi / 2, math.pi / 2, 0, 2 * math.pi / 3],
            [math.pi / 2, math.pi, 2 * math.pi / 3, 0],
        ]
    )
    np.testing.assert_allclose(d, expected, atol=1e-7)


# --------------------------------------------------------------------- truncation


@pytest.mark.parametrize("variant", ["so3", "s3", "paper"])
@pytest.mark.parametrize("kappa", [0.05, 0.1, 0.3, 1.0, 2.5])
def test_truncation_bound_holds_against_long_series(variant: str, kappa: float) -> None:
    x = np.concatenate([np.linspace(-1.0, 1.0, 401), np.cos(np.linspace(0.0, 1e-3, 20))])
    n_long = 4 * heat_kernel_num_terms(kappa, 1e-15, variant) + 100
    reference = heat_series(x, kappa, n_long, variant)
    previous_n = -1
    for tol in (1e-3, 1e-6, 1e-9, 1e-12):
        n_max = heat_kernel_num_terms(kappa, tol, variant)
        assert n_max >= previous_n
        previous_n = n_max
        bound = heat_kernel_truncation_bound(kappa, n_max, variant)
        assert bound <= tol
        err = np.max(np.abs(heat_series(x, kappa, n_max, variant) - reference))
        assert err <= bound + 1e-14, (tol, n_max, err, bound)
        if n_max > 0:  # minimality of the returned number of terms
            assert heat_kernel_truncation_bound(kappa, n_max - 1, variant) > tol


@pytest.mark.parametrize("kappa", [0.05, 0.3, 1.0])
def test_s3_series_matches_closed_form_heat_kernel(kappa: float) -> None:
    """Independent check of the Gegenbauer coefficients: the S3 heat kernel has the image-sum
    closed form p_t(th) = (4 pi t)^-1.5 e^t sum_k (th + 2 pi k)/sin(th) exp(-(th+2 pi k)^2/4t)."""
    t = kappa**2 / 2.0
    theta = np.linspace(0.05, math.pi - 0.05, 60)
    ks = np.arange(-30, 31)[:, None]
    shifted = theta[None, :] + 2.0 * math.pi * ks
    closed = (
        (4.0 * math.pi * t) ** -1.5
        * math.exp(t)
        * np.sum(shifted * np.exp(-(shifted**2) / (4.0 * t)), axis=0)
        / np.sin(theta)
    )
    n_max = heat_kernel_num_terms(kappa, 1e-14, "s3")
    n = np.arange(n_max + 1)
    norm = np.sum((n + 1.0) ** 2 * np.exp(-t * n * (n + 2.0))) / (2.0 * math.pi**2)
    series = heat_series(np.cos(theta), kappa, n_max, "s3") * norm
    np.testing.assert_allclose(series, closed, rtol=1e-10, atol=1e-12 * closed.max())


def test_so3_variant_is_symmetrised_s3_kernel() -> None:
    rng = np.random.default_rng(5)
    qa, qb = random_quats(rng, 7), random_quats(rng, 6)
    kappa = 0.35
    k_plus = s3_heat_kernel(qa, qb, kappa, variant="s3")
    k_minus = s3_heat_kernel(qa, -qb, kappa, variant="s3")
    # Normalisation: S3 value at identical points vs its antipodal value.
    k_anti = s3_heat_kernel(qa[:1], -qa[:1], kappa, variant="s3")[0, 0]
    expected = (k_plus + k_minus) / (1.0 + k_anti)
    np.testing.assert_allclose(s3_heat_kernel(qa, qb, kappa, variant="so3"), expected, atol=1e-11)


# --------------------------------------------------------------------------- GP


def smooth_objective(poses: np.ndarray) -> np.ndarray:
    """Smooth on S3 x R3 and well defined on rotations (rotation-matrix entries)."""
    w, x, y, z = poses[:, :4].T
    r22 = 1.0 - 2.0 * (x * x + y * y)
    r01 = 2.0 * (x * y - w * z)
    p = poses[:, 4:]
    return r22 + 0.5 * r01 + np.sin(3.0 * p[:, 0]) + 2.0 * p[:, 1] * p[:, 2]


def test_gp_recovers_smooth_function_on_held_out_poses() -> None:
    rng = np.random.default_rng(11)
    train, test = random_poses(rng, 80), random_poses(rng, 300)
    noise_std = 0.01
    y = smooth_objective(train) + noise_std * rng.normal(size=80)
    gp = PoseGP().fit(train, y)
    mean, var = gp.predict(test)
    truth = smooth_objective(test)
    rmse_gp = math.sqrt(np.mean((mean - truth) ** 2))
    rmse_prior = math.sqrt(np.mean((np.mean(y) - truth) ** 2))
    assert rmse_gp < 0.5 * rmse_prior, (rmse_gp, rmse_prior)
    # Uncertainty is informative: most held-out errors lie within 3 predictive std.
    inside = np.abs(mean - truth) <= 3.0 * np.sqrt(var + gp.hyper.noise_var)
    assert np.mean(inside) >= 0.9
    # The so3 kernel sees q and -q as the same pose.
    flipped = test.copy()
    flipped[:, :4] *= -1.0
    np.testing.assert_allclose(gp.predict(flipped)[0], mean, atol=1e-9)
    assert np.isfinite(gp.log_marginal_likelihood)


def test_gp_prediction_interpolates_training_data_with_small_noise() -> None:
    rng = np.random.default_rng(12)
    train = random_poses(rng, 25)
    y = smooth_objective(train)
    hyper = GPHyperparameters(kappa=0.5, lengthscale_m=0.5, signal_var=1.0, noise_var=1e-8)
    gp = PoseGP(hyper).fit(train, y, optimize=False)
    mean, var = gp.predict(train)
    np.testing.assert_allclose(mean, y, atol=1e-4)
    assert np.all(var < 1e-6)


def test_ucb_picks_max_variance_point_when_mean_is_flat() -> None:
    rng = np.random.default_rng(13)
    centre = np.array([1.0, 0.0, 0.0, 0.0, 0.3, 0.0, 0.4])
    measured = np.repeat(centre[None, :], 12, axis=0)
    measured[:, :4] += 0.05 * rng.normal(size=(12, 4))
    measured[:, :4] /= np.linalg.norm(measured[:, :4], axis=1, keepdims=True)
    measured[:, 4:] += 0.02 * rng.normal(size=(12, 3))
    y = np.full(12, -0.3)  # flat objective: the posterior mean is flat everywhere
    candidates = np.vstack([measured[:6], random_poses(rng, 15, half_width_m=0.05)])
    candidates[:6, 4:] += 0.005
    far = np.array([0.0, S, S, 0.0, -0.6, 0.6, -0.2])
    candidates = np.vstack([candidates[:9], far, candidates[9:]])
    for optimize in (False, True):
        gp = PoseGP().fit(measured, y, optimize=optimize)
        mean, var = gp.predict(candidates)
        np.testing.assert_allclose(mean, -0.3, atol=1e-12)
        assert int(np.argmax(gp.ucb(candidates, beta=4.0))) == int(np.argmax(var))
        idx = select_next_pose(
            candidates, measured, y, beta_schedule="srinivas", optimize_hyperparameters=optimize
        )
        assert idx == int(np.argmax(var))
    # The farthest pose from every measurement is the most uncertain one (fixed kernel).
    gp = PoseGP().fit(measured, y, optimize=False)
    assert int(np.argmax(gp.predict(candidates)[1])) == 9


def test_select_next_pose_trades_mean_against_variance() -> None:
    # Two unmeasured candidates with equal variance: UCB prefers the higher mean.
    rng = np.random.default_rng(14)
    measured = random_poses(rng, 30)
    y = measured[:, 4]  # objective increases with x
    hyper = GPHyperparameters(kappa=1.0, lengthscale_m=0.4, signal_var=1.0, noise_var=1e-4)
    cand = measured[[0, 0]].copy()
    cand[0, 4], cand[1, 4] = -0.45, 0.45
    cand[:, 5:] = 0.0
    idx = select_next_pose(
        cand, measured, y, hyperparameters=hyper, optimize_hyperparameters=False, beta_schedule=1.0
    )
    assert idx == 1


def test_gp_ucb_loop_finds_good_pose_faster_than_random() -> None:
    rng = np.random.default_rng(15)
    candidates = random_poses(rng, 400)
    values = smooth_objective(candidates)
    q95 = np.quantile(values, 0.95)
    measured_idx = list(rng.choice(400, size=5, replace=False))
    for _ in range(20):
        idx = select_next_pose(candidates, candidates[measured_idx], values[measured_idx])
        measured_idx.append(idx)
    best_ucb = values[measured_idx].max()
    # A random design of the same size reaches the top 5 % with probability ~1-0.95^25 = 0.72;
    # GP-UCB must get there, and beat the median random best over 200 random designs.
    random_best = [values[rng.choice(400, 25, replace=False)].max() for _ in range(200)]
    assert best_ucb >= q95
    assert best_ucb > np.median(random_best)


def test_empty_measurements_return_first_candidate() -> None:
    rng = np.random.default_rng(16)
    candidates = random_poses(rng, 5)
    assert select_next_pose(candidates, np.zeros((0, 7)), np.zeros(0)) == 0


# ------------------------------------------------------------------ beta, objective


def test_srinivas_beta_schedule() -> None:
    b = [srinivas_beta(t, 100, 0.1) for t in range(1, 30)]
    assert all(b2 > b1 for b1, b2 in zip(b, b[1:], strict=False))
    assert b[0] == pytest.approx(2.0 * math.log(100 * math.pi**2 / 0.6))
    with pytest.raises(ValueError, match="iteration"):
        srinivas_beta(0, 10)
    with pytest.raises(ValueError, match="delta"):
        srinivas_beta(1, 10, delta=1.5)


def test_pose_error_objective_follows_paper_eq6() -> None:
    e_p = np.array([0.0, 1e-3, 4e-3, 2e-3])
    e_r = np.array([0.02, 0.0, 0.01, 0.005])
    f = pose_error_objective(e_p, e_r, w_pos=0.7, w_rot=0.3)
    np.testing.assert_allclose(f, -(0.7 * e_p / 4e-3 + 0.3 * e_r / 0.02))
    assert np.all(f <= 0.0) and np.all(f >= -1.0)
    # Weights are rescaled to sum to one.
    np.testing.assert_allclose(pose_error_objective(e_p, e_r, 7.0, 3.0), f)
    # Position-only tracker.
    np.testing.assert_allclose(pose_error_objective(e_p), -e_p / 4e-3)
    # Error vectors are reduced to norms; fixed scales; positive cost.
    vec = np.array([[0, 0, 0], [0.6e-3, 0.8e-3, 0], [0, 0, 4e-3], [2e-3, 0, 0]], dtype=float)
    np.testing.assert_allclose(pose_error_objective(vec), -e_p / 4e-3)
    np.testing.assert_allclose(
        pose_error_objective(e_p, e_r, pos_scale_m=1e-2, rot_scale_rad=0.1, negate=False),
        0.5 * e_p / 1e-2 + 0.5 * e_r / 0.1,
    )
    np.testing.assert_allclose(pose_error_objective(np.zeros(3)), 0.0)
    with pytest.raises(ValueError, match="non-negative"):
        pose_error_objective(np.array([-1.0]))
    with pytest.raises(ValueError, match="rot_err_rad"):
        pose_error_objective(e_p, e_r[:2])


def test_input_validation_messages() -> None:
    good = random_poses(np.random.default_rng(17), 3)
    with pytest.raises(ValueError, match=r"\(N, 7\)"):
        pose_product_kernel(good[:, :6], good)
    bad = good.copy()
    bad[1, :4] *= 2.0
    with pytest.raises(ValueError, match="unit norm"):
        pose_product_kernel(bad, good)
    with pytest.raises(ValueError, match="kappa"):
        s3_heat_kernel(good[:, :4], good[:, :4], -1.0)
    with pytest.raises(ValueError, match="variant"):
        s3_heat_kernel(good[:, :4], good[:, :4], 0.5, variant="foo")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="y must have shape"):
        PoseGP().fit(good, np.zeros(2))
    with pytest.raises(ValueError, match="beta_schedule"):
        select_next_pose(good, good, np.zeros(3), beta_schedule="nope")
    with pytest.raises(ValueError, match="candidate_poses is empty"):
        select_next_pose(np.zeros((0, 7)), good, np.zeros(3))
