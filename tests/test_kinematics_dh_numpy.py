"""The numpy nominal forward kinematics (used by the recording screen, so that `workcell info`
does not load JAX) equals the estimation's JAX chain."""

import numpy as np
import pytest

from workcell.kinematics.chain import base_T_flange, pack
from workcell.kinematics.dh_numpy import base_T_flange_nominal
from workcell.kinematics.robots import CATALOGUE, DH


@pytest.mark.parametrize("model", sorted(CATALOGUE))
def test_equals_the_jax_chain(model):
    rng = np.random.default_rng(7)
    dh = CATALOGUE[model].dh
    off = DH(a=dh.a, d=dh.d, alpha=dh.alpha, theta_offset=rng.normal(0, 0.01, 6))
    q = rng.uniform(-np.pi, np.pi, (50, 6))
    for d in (dh, off):
        np.testing.assert_allclose(
            base_T_flange_nominal(d, q), np.asarray(base_T_flange(pack(d), q)), atol=1e-12
        )


def test_shape_is_checked():
    with pytest.raises(ValueError, match=r"expected shape \(N, 6\), got \(6,\)"):
        base_T_flange_nominal(CATALOGUE["ur5e"].dh, np.zeros(6))
