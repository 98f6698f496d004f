"""Forward kinematics and Jacobians against an independent slow implementation and finite
differences; gravity torques against the derivative of the potential energy."""

import numpy as np
import pytest

from workcell.kinematics import chain
from workcell.kinematics.frames import (
    check_transform,
    kabsch,
    matrix_from_quat_wxyz,
    matrix_from_rotvec,
    quat_wxyz_from_matrix,
    transform_from,
)
from workcell.kinematics.gravity import G_BASE, gravity_torques_nm
from workcell.kinematics.robots import UR5E, UR10, robot_from_session


def slow_fk(a, d, alpha, off, beta, base_T, tool, q):
    """Textbook standard DH, one pose at a time, plain Python floats."""
    T = base_T.copy()
    for i in range(6):
        th = q[i] + off[i]
        ct, st, ca, sa = np.cos(th), np.sin(th), np.cos(alpha[i]), np.sin(alpha[i])
        A = np.array(
            [
                [ct, -st * ca, st * sa, a[i] * ct],
                [st, ct * ca, -ct * sa, a[i] * st],
                [0, sa, ca, d[i]],
                [0, 0, 0, 1.0],
            ]
        )
        cb, sb = np.cos(beta[i]), np.sin(beta[i])
        Ry = np.array([[cb, 0, sb, 0], [0, 1, 0, 0], [-sb, 0, cb, 0], [0, 0, 0, 1.0]])
        T = T @ A @ Ry
    return (T @ np.append(tool, 1.0))[:3]


@pytest.mark.parametrize("spec", [UR5E, UR10])
def test_fk_matches_slow_implementation(spec):
    rng = np.random.default_rng(3)
    for _ in range(5):
        theta = chain.pack(spec.dh, tool=rng.normal(0, 0.05, 3)) + rng.normal(0, 1e-3, 39)
        base_ref = transform_from(matrix_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 2, 3))
        q = rng.uniform(-np.pi, np.pi, (20, 6))
        got = np.asarray(chain.p_tracker(theta, base_ref, q))
        base_T = base_ref @ transform_from(matrix_from_rotvec(theta[33:36]), np.zeros(3))
        base_T = (
            base_ref
            @ transform_from(np.eye(3), theta[30:33])
            @ transform_from(matrix_from_rotvec(theta[33:36]), np.zeros(3))
        )
        want = np.array(
            [
                slow_fk(
                    theta[0:6],
                    theta[6:12],
                    theta[12:18],
                    theta[18:24],
                    theta[24:30],
                    base_T,
                    theta[36:39],
                    qi,
                )
                for qi in q
            ]
        )
        np.testing.assert_allclose(got, want, atol=1e-12)


def test_ur5e_home_pose_matches_published_geometry():
    # all joints zero: arm stretched along -x of base; flange at x = a2 + a3, z = d1 - d5,
    # y = -(d4 + d6) for the UR DH convention
    theta = chain.pack(UR5E.dh)
    T = np.asarray(chain.base_T_flange(theta, np.zeros((1, 6))))[0]
    np.testing.assert_allclose(
        T[:3, 3], [-0.425 - 0.3922, -(0.1333 + 0.0996), 0.1625 - 0.0997], atol=1e-12
    )


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(5)
    theta = chain.pack(UR5E.dh, tool=(0.01, -0.02, 0.06)) + rng.normal(0, 1e-3, 39)
    base_ref = transform_from(matrix_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 2, 3))
    q = rng.uniform(-3, 3, (4, 6))
    Jp = np.asarray(chain.jac_params(theta, base_ref, q))
    Jq = np.asarray(chain.jac_joints(theta, base_ref, q))
    h = 1e-6
    for k in range(39):
        e = np.zeros(39)
        e[k] = h
        fd = (
            np.asarray(chain.p_tracker(theta + e, base_ref, q))
            - np.asarray(chain.p_tracker(theta - e, base_ref, q))
        ) / (2 * h)
        np.testing.assert_allclose(Jp[:, :, k], fd, atol=1e-8, err_msg=chain.PARAM_NAMES[k])
    for j in range(6):
        e = np.zeros(6)
        e[j] = h
        fd = (
            np.asarray(chain.p_tracker(theta, base_ref, q + e))
            - np.asarray(chain.p_tracker(theta, base_ref, q - e))
        ) / (2 * h)
        np.testing.assert_allclose(Jq[:, :, j], fd, atol=1e-8)


@pytest.mark.parametrize("n", [6, 7])
def test_analytic_joint_jacobian_matches_autodiff(n):
    """The analytic dp/dq used by the LDDMM evaluation equals jax.jacfwd of the FK, with every
    parameter perturbed (Hayati betas, offsets, base pose, tool) and for 6 and 7 joints."""
    import jax

    rng = np.random.default_rng(11 + n)
    theta = rng.normal(0, 0.3, 5 * n + 9)
    base_ref = transform_from(matrix_from_rotvec(rng.normal(0, 1, 3)), rng.normal(0, 2, 3))
    for q in rng.uniform(-3, 3, (5, n)):
        p, J = chain.p_tracker_and_jacobian_single(theta, base_ref, q)
        p_ref = chain.p_tracker_single(theta, base_ref, q)
        J_ref = jax.jacfwd(lambda qq: chain.p_tracker_single(theta, base_ref, qq))(q)
        assert np.shape(J) == (3, n)
        np.testing.assert_allclose(p, p_ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(J, J_ref, rtol=0, atol=1e-12)


def test_gravity_torque_is_minus_gradient_of_potential_energy():
    spec = UR10
    theta = chain.pack(spec.dh)
    rng = np.random.default_rng(1)
    payload, pcom = 2.0, np.array([0.0, 0.01, 0.05])

    def potential(q):
        T = np.asarray(chain.base_T_frames(theta, q[None]))[0]
        V = 0.0
        for j in range(6):
            c = T[j + 1, :3, :3] @ spec.link_coms_m[j] + T[j + 1, :3, 3]
            V -= spec.link_masses_kg[j] * G_BASE @ c
        c = T[6, :3, :3] @ pcom + T[6, :3, 3]
        return V - payload * G_BASE @ c

    q = rng.uniform(-2, 2, (5, 6))
    tau = gravity_torques_nm(spec, q, payload, pcom)
    for n in range(len(q)):
        for i in range(6):
            e = np.zeros(6)
            e[i] = 1e-6
            dV = (potential(q[n] + e) - potential(q[n] - e)) / 2e-6
            assert tau[n, i] == pytest.approx(-dV, abs=1e-5)


def test_frames_round_trips_and_validators():
    rng = np.random.default_rng(0)
    for _ in range(20):
        R = matrix_from_rotvec(rng.normal(0, 2, 3))
        np.testing.assert_allclose(matrix_from_quat_wxyz(quat_wxyz_from_matrix(R)), R, atol=1e-12)
        T = transform_from(R, rng.normal(size=3))
        p = rng.normal(size=(10, 3))
        q = p @ R.T + T[:3, 3]
        np.testing.assert_allclose(kabsch(p, q), T, atol=1e-10)
    with pytest.raises(ValueError, match=r"\(3, 3\)"):
        check_transform(np.eye(3))
    with pytest.raises(ValueError, match="expected shape"):
        chain.check_joints(np.zeros((3, 5)))
    with pytest.raises(ValueError, match="non-finite"):
        chain.check_joints(np.full((1, 6), np.nan))


def test_robot_from_session_accepts_any_dh_and_rejects_bad():
    dh = {"a": [0.1] * 6, "d": [0.2] * 6, "alpha": [0.3] * 6, "theta_offset": [0.0] * 6}
    spec = robot_from_session({"model": "my-arm", "dh": dh})
    assert spec.model == "my-arm" and spec.dh.a[0] == 0.1
    with pytest.raises(ValueError, match="unknown robot"):
        robot_from_session({"model": "nonexistent"})
    with pytest.raises(ValueError, match="6 values"):
        robot_from_session({"model": "x", "dh": {**dh, "a": [0.1] * 5}})
    with pytest.raises(ValueError, match="6-joint"):  # recordings describe 6-joint arms only
        robot_from_session({"model": "x", "dh": {k: v + [0.0] for k, v in dh.items()}})
