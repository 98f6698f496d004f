"""Bayesian optimal experimental design on S3 x R3 (seed 002: Das, Touma & Burdick).

``kernels``: heat kernel on unit quaternions, SE kernel on positions, their product over poses
``(N, 7) = [qw qx qy qz px py pz]`` and the naive geodesic kernel (counter-example).
``gp``: GP regression with those kernels, GP-UCB (:func:`ucb_scores`, :func:`select_next_pose`).
"""

from workcell.estimation.design.gp import (
    GPHyperparameters,
    PoseGP,
    pose_error_objective,
    select_next_pose,
    srinivas_beta,
    ucb_scores,
)
from workcell.estimation.design.kernels import (
    heat_kernel_num_terms,
    heat_kernel_truncation_bound,
    naive_geodesic_kernel,
    naive_se3_kernel,
    pose_product_kernel,
    quaternion_geodesic_distance,
    s3_heat_kernel,
    se_kernel_r3,
)

__all__ = [
    "GPHyperparameters",
    "PoseGP",
    "heat_kernel_num_terms",
    "heat_kernel_truncation_bound",
    "naive_geodesic_kernel",
    "naive_se3_kernel",
    "pose_error_objective",
    "pose_product_kernel",
    "quaternion_geodesic_distance",
    "s3_heat_kernel",
    "se_kernel_r3",
    "select_next_pose",
    "srinivas_beta",
    "ucb_scores",
]
