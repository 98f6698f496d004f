"""Landmark geodesic shooting for calibration by diffeomorphisms (Orozco & Ratajczak, eqs. 27-29).

Notation (per measurement / landmark i = 1..N):
  x_i in X (R^n)      fixed joint configuration (Eulerian point, as in the paper)
  q_i in Y (R^m)      q_i(t) = k_t(x_i), starts at k0(x_i)
  J_i (m, n)          J_i(t) = Dk_t(x_i), starts at Dk0(x_i)
  P_i in Y* (R^m)     momentum, P_i(0) = P0_i is the unknown of the fit

Vector fields (RKHS representers, eq. 26 with the momentum map of eq. 16):
  w_t(y) =  lam_w * sum_j K_W(y, q_j) P_j                       (field on Y, generates psi)
  v_t(x) = -lam_v * sum_j K_V(x, x_j) J_j^T P_j                 (field on X, generates phi)
The minus sign in v is the one of the momentum map (16), u^flat = (-Dk^T P, P); eq. (28) as
printed drops it. With the sign of (16) the landmark equations are the Hamiltonian flow of

  H(q, J, P) = 1/2 lam_w sum_ij P_i^T K_W(q_i,q_j) P_j
             + 1/2 lam_v sum_ij P_i^T J_i K_V(x_i,x_j) J_j^T P_j           (= the two energy
                                                                               terms of (27))
  dq_i/dt =  dH/dP_i = w(q_i) - J_i v(x_i)
  dP_i/dt = -dH/dq_i = -Dw(q_i)^T P_i
  dJ_i/dt = Dw(q_i) J_i - J_i Dv(x_i)                                       (eq. 23)

Two documented deviations from the printed (28):
  * the sign of v (above);
  * the term -div(P v^T) of (28) is the continuum integration by parts of the J-dependence of H
    (note dH/dJ_i = -P_i v(x_i)^T). For Dirac momenta held at fixed Eulerian points it has no
    pointwise value (its transport part is a derivative of a Dirac). It is therefore left out
    by default; `div_term=True` adds the pointwise approximation -P_i (div v)(x_i) (the paper's
    term with P treated as locally constant). With div_term=False the (q, P) part is exactly
    Hamiltonian; J is not a canonical variable, so H is conserved exactly only when lam_v = 0
    (psi only) and drifts by O(|P|^3) otherwise (see tests).
The weights lam_v / lam_w select the model: (1,1) both diffeomorphisms (default), (0,1) psi only,
(1,0) phi only.

Integration: fixed-step classical RK4 on t in [0, 1]; the whole trajectory is a `lax.scan`, so
gradients of the cost (27) w.r.t. P0 come from reverse-mode autodiff through the integrator.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

from workcell._jax import jax, jnp
from workcell.estimation.lddmm.kernels import gauss, gauss_gemm, gauss_point


class KernelParams(NamedTuple):
    """Kernel widths (X in the units of x, Y in the units of y) and field weights."""

    sigma_v: float
    sigma_w: float
    lam_v: float = 1.0
    lam_w: float = 1.0


class State(NamedTuple):
    q: jnp.ndarray  # (N, m)
    J: jnp.ndarray  # (N, m, n)
    P: jnp.ndarray  # (N, m)


class StageData(NamedTuple):
    """Landmark quantities at every RK4 stage, needed to evaluate the fields elsewhere (eq. 29).

    Leading axes (n_steps, 4). `a` = -lam_v J^T P (so v(x) = sum_j K_V(x, x_j) a_j),
    `b` = lam_w P (so w(y) = sum_j K_W(y, q_j) b_j).
    """

    q: jnp.ndarray  # (S, 4, N, m)
    a: jnp.ndarray  # (S, 4, N, n)
    b: jnp.ndarray  # (S, 4, N, m)


# --------------------------------------------------------------------------------------------
# Hamiltonian and the two right-hand sides
# --------------------------------------------------------------------------------------------


def hamiltonian(state: State, x: jnp.ndarray, kp: KernelParams) -> jnp.ndarray:
    """Kinetic energy H(q, J, P) of the landmark system = regulariser of (27)."""
    q, J, P = state
    kw = gauss(q, q, kp.sigma_w)
    kv = gauss(x, x, kp.sigma_v)
    jtp = jnp.einsum("imn,im->in", J, P)
    return 0.5 * kp.lam_w * jnp.sum(kw * (P @ P.T)) + 0.5 * kp.lam_v * jnp.sum(kv * (jtp @ jtp.T))


def _w_field(state: State, kp: KernelParams):
    def w(y):
        return kp.lam_w * gauss_point(y, state.q, kp.sigma_w) @ state.P

    return w


def _v_field(state: State, x: jnp.ndarray, kp: KernelParams):
    a = -kp.lam_v * jnp.einsum("imn,im->in", state.J, state.P)

    def v(xi):
        return gauss_point(xi, x, kp.sigma_v) @ a

    return v


def rhs_autodiff(state: State, x: jnp.ndarray, kp: KernelParams) -> State:
    """(q, P) dynamics from jax.grad of the Hamiltonian; J from (23) with Dw, Dv by jax.jacfwd."""
    dH_dq, dH_dP = jax.grad(lambda q, P: hamiltonian(State(q, state.J, P), x, kp), argnums=(0, 1))(
        state.q, state.P
    )
    dw = jax.vmap(jax.jacfwd(_w_field(state, kp)))(state.q)  # (N, m, m)
    dv = jax.vmap(jax.jacfwd(_v_field(state, x, kp)))(x)  # (N, n, n)
    dJ = jnp.einsum("iab,ibn->ian", dw, state.J) - jnp.einsum("imk,ikn->imn", state.J, dv)
    return State(dH_dP, dJ, -dH_dq)


def _kouter(k: jnp.ndarray, a: jnp.ndarray, c: jnp.ndarray) -> jnp.ndarray:
    """sum_j k_ij a_j c_j^T as one matrix product: (B,N),(N,p),(N,r) -> (B,p,r)."""
    N, p = a.shape
    r = c.shape[1]
    return (k @ (a[:, :, None] * c[:, None, :]).reshape(N, p * r)).reshape(k.shape[0], p, r)


def fields_at_landmarks(
    state: State, x: jnp.ndarray, kv: jnp.ndarray, kp: KernelParams
) -> tuple[jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray, jnp.ndarray]:
    """Closed-form w, Dw at q_i and v, Dv at x_i (Gaussian kernel gradients)."""
    q, J, P = state
    kw = gauss(q, q, kp.sigma_w)
    b = kp.lam_w * P
    w = kw @ b  # (N, m)
    # Dw_i = 1/sw^2 sum_j K_ij b_j (q_j - q_i)^T
    dw = (_kouter(kw, b, q) - w[:, :, None] * q[:, None, :]) / kp.sigma_w**2
    a = -kp.lam_v * jnp.einsum("imn,im->in", J, P)
    v = kv @ a  # (N, n)
    dv = (_kouter(kv, a, x) - v[:, :, None] * x[:, None, :]) / kp.sigma_v**2
    return w, dw, v, dv, a, b


def rhs_explicit(
    state: State,
    x: jnp.ndarray,
    kp: KernelParams,
    kv: jnp.ndarray | None = None,
    div_term: bool = False,
) -> State:
    """System (28) written out (sign of v per (16); see module docstring for `div_term`).

    `kv` = K_V(x, x) may be passed precomputed (it is constant: the x_i do not move).
    """
    if kv is None:
        kv = gauss(x, x, kp.sigma_v)
    q, J, P = state
    w, dw, v, dv, _, _ = fields_at_landmarks(state, x, kv, kp)
    dq = w - jnp.einsum("imn,in->im", J, v)
    dP = -jnp.einsum("iam,ia->im", dw, P)
    if div_term:
        dP = dP - P * jnp.trace(dv, axis1=1, axis2=2)[:, None]
    dJ = jnp.einsum("iab,ibn->ian", dw, J) - jnp.einsum("imk,ikn->imn", J, dv)
    return State(dq, dJ, dP)


# --------------------------------------------------------------------------------------------
# RK4 shooting
# --------------------------------------------------------------------------------------------


def _axpy(h, k, s):
    return jax.tree_util.tree_map(lambda a, b: a + h * b, s, k)


def shoot(
    state0: State,
    x: jnp.ndarray,
    kp: KernelParams,
    n_steps: int,
    div_term: bool = False,
    record: bool = False,
):
    """Integrate the landmark system from t=0 to 1 with `n_steps` RK4 steps.

    Returns the final state, and with record=True also the StageData for eq. (29) and the
    state at every step boundary (n_steps+1 leading axis, for diagnostics).
    """
    h = 1.0 / n_steps
    kv = gauss(x, x, kp.sigma_v)

    def f(s):
        return rhs_explicit(s, x, kp, kv=kv, div_term=div_term)

    def stage_data(s):
        a = -kp.lam_v * jnp.einsum("imn,im->in", s.J, s.P)
        return s.q, a, kp.lam_w * s.P

    def step(s, _):
        s1 = s
        k1 = f(s1)
        s2 = _axpy(0.5 * h, k1, s)
        k2 = f(s2)
        s3 = _axpy(0.5 * h, k2, s)
        k3 = f(s3)
        s4 = _axpy(h, k3, s)
        k4 = f(s4)
        new = jax.tree_util.tree_map(
            lambda y, a, b, c, d: y + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d), s, k1, k2, k3, k4
        )
        if record:
            sd = [stage_data(z) for z in (s1, s2, s3, s4)]
            out = (tuple(jnp.stack([d[i] for d in sd]) for i in range(3)), new)
        else:
            out = None
        return new, out

    final, rec = jax.lax.scan(step, state0, None, length=n_steps)
    if not record:
        return final
    (sq, sa, sb), states = rec
    traj = jax.tree_util.tree_map(lambda a0, r: jnp.concatenate([a0[None], r]), state0, states)
    return final, StageData(sq, sa, sb), traj


# --------------------------------------------------------------------------------------------
# Evaluation at new configurations (eq. 29) and the flows phi, psi
# --------------------------------------------------------------------------------------------

_C = (0.0, 0.5, 0.5, 1.0)


def _rk4_with_stages(y0, stages_fn, n_steps):
    """Generic RK4 where the RHS at (step, stage r) is stages_fn(step_data[r], y)."""
    h = 1.0 / n_steps

    def step(y, sd):
        def f(r, yy):
            return stages_fn(jax.tree_util.tree_map(lambda a: a[r], sd), yy)

        k1 = f(0, y)
        k2 = f(1, _axpy(0.5 * h, k1, y))
        k3 = f(2, _axpy(0.5 * h, k2, y))
        k4 = f(3, _axpy(h, k3, y))
        return (
            jax.tree_util.tree_map(
                lambda y_, a, b, c, d: y_ + (h / 6.0) * (a + 2.0 * b + 2.0 * c + d),
                y,
                k1,
                k2,
                k3,
                k4,
            ),
            None,
        )

    return step


def evolve_kinematics(
    xi: jnp.ndarray,
    k0_xi: jnp.ndarray,
    dk0_xi: jnp.ndarray,
    x: jnp.ndarray,
    sd: StageData,
    kp: KernelParams,
    f32: bool = False,
    frozen_jacobian: bool = False,
) -> jnp.ndarray:
    """Eq. (29): k_1(xi) for a batch xi (B, n) given k0(xi) (B, m) and Dk0(xi) (B, m, n).

    The landmark fields at each RK4 stage come from `sd`, so for xi = x_i this reproduces the
    fitted q_i(1) (same integrator, same stages). K_V(xi, x_j) is computed once (the x_j are
    fixed), all stages of v and Dv come from one matrix product. The state integrated is the
    displacement u = k - k0(xi) (small), so k0 keeps its float64 value.

    f32=True: kernels, fields and the displacement in float32, on coordinates centred on the
    landmarks (the Gaussian kernel and the field gradients are translation invariant), so the
    rounding is relative to the landmark spread and to |u|, not to the absolute coordinates;
    k0(xi) is added back in float64. frozen_jacobian=True: approximation Dk_t(xi) = Dk0(xi)
    in the term Dk_t v (drops the Dv and Dw evaluations, the bulk of the cost); its effect on
    k is second order in the deformation and is measured, not assumed (`tune_evaluation`).
    Both flags are static arguments under jit.
    """
    n_steps = sd.q.shape[0]
    n = x.shape[1]
    N = x.shape[0]
    dt = jnp.float32 if f32 else xi.dtype
    cx = jnp.mean(x, axis=0)
    cy = jnp.mean(sd.q[0, 0], axis=0)
    xi_c = (xi - cx).astype(dt)
    x_c = (x - cx).astype(dt)
    k0c = (k0_xi - cy).astype(dt)
    sq = (sd.q - cy).astype(dt)
    sa = sd.a.astype(dt)
    sb = sd.b.astype(dt)
    sv = jnp.asarray(kp.sigma_v, dtype=dt)
    sw = jnp.asarray(kp.sigma_w, dtype=dt)
    inv_v = 1.0 / (sv * sv)
    inv_w = 1.0 / (sw * sw)
    kvx = gauss_gemm(xi_c, x_c, sv)  # (B, N)
    if frozen_jacobian:
        return _evolve_frozen(kvx, k0_xi, k0c, dk0_xi.astype(dt), sq, sa, sb, sw, n_steps)
    # v and sum_j K a_j x_j^T for all stages at once
    a_all = jnp.moveaxis(sa, 2, 0)  # (N, S, 4, n)
    ax_all = a_all[..., :, None] * x_c[:, None, None, None, :]  # (N, S, 4, n, n)
    v_all = (kvx @ a_all.reshape(N, -1)).reshape(xi.shape[0], n_steps, 4, n)
    kax = (kvx @ ax_all.reshape(N, -1)).reshape(xi.shape[0], n_steps, 4, n, n)
    dv_all = (kax - v_all[..., :, None] * xi_c[:, None, None, None, :]) * inv_v
    v_all = jnp.moveaxis(v_all, 0, 2)  # (S, 4, B, n)
    dv_all = jnp.moveaxis(dv_all, 0, 2)  # (S, 4, B, n, n)

    def rhs(stage, y):
        u, dk = y
        k = k0c + u
        q, b, v, dv = stage
        kw = gauss_gemm(k, q, sw)  # (B, N)
        w = kw @ b
        kbq = (kw @ (b[:, :, None] * q[:, None, :]).reshape(q.shape[0], -1)).reshape(
            k.shape[0], k.shape[1], k.shape[1]
        )
        dw = (kbq - w[:, :, None] * k[:, None, :]) * inv_w
        dk_dot = jnp.einsum("bij,bjn->bin", dw, dk) - jnp.einsum("bmk,bkn->bmn", dk, dv)
        k_dot = w - jnp.einsum("bmn,bn->bm", dk, v)
        return (k_dot, dk_dot)

    step = _rk4_with_stages(None, rhs, n_steps)
    u0 = jnp.zeros_like(k0c)
    (u1, _), _ = jax.lax.scan(step, (u0, dk0_xi.astype(dt)), (sq, sb, v_all, dv_all))
    return k0_xi + u1.astype(k0_xi.dtype)


def _evolve_frozen(kvx, k0_xi, k0c, dk0, sq, sa, sb, sw, n_steps):
    B, n = kvx.shape[0], sa.shape[-1]
    N = kvx.shape[1]
    v_all = (kvx @ jnp.moveaxis(sa, 2, 0).reshape(N, -1)).reshape(B, n_steps, 4, n)
    jv_all = jnp.moveaxis(jnp.einsum("bmn,bsrn->bsrm", dk0, v_all), 0, 2)  # (S, 4, B, m)

    def rhs(stage, u):
        q, b, jv = stage
        return gauss_gemm(k0c + u, q, sw) @ b - jv

    step = _rk4_with_stages(None, rhs, n_steps)
    u1, _ = jax.lax.scan(step, jnp.zeros_like(k0c), (sq, sb, jv_all))
    return k0_xi + u1.astype(k0_xi.dtype)


def flow_psi(y0: jnp.ndarray, sd: StageData, kp: KernelParams) -> tuple[jnp.ndarray, jnp.ndarray]:
    """psi_1 and det D psi_1 at points y0 (B, m): flow of w_t on Y (Lagrangian)."""
    n_steps = sd.q.shape[0]
    m = y0.shape[1]

    def rhs(stage, s):
        y, D = s
        q, b = stage
        kw = gauss_gemm(y, q, kp.sigma_w)
        w = kw @ b
        kbq = _kouter(kw, b, q)
        dw = (kbq - w[:, :, None] * y[:, None, :]) / kp.sigma_w**2
        return (w, jnp.einsum("bij,bjk->bik", dw, D))

    step = _rk4_with_stages(None, rhs, n_steps)
    D0 = jnp.broadcast_to(jnp.eye(m), (y0.shape[0], m, m))
    (y1, D1), _ = jax.lax.scan(step, (y0, D0), (sd.q, sd.b))
    return y1, jnp.linalg.det(D1)


def flow_phi(
    x0: jnp.ndarray, x: jnp.ndarray, sd: StageData, kp: KernelParams
) -> tuple[jnp.ndarray, jnp.ndarray]:
    """phi_1 and det D phi_1 at points x0 (B, n): flow of v_t on X (Lagrangian)."""
    n_steps = sd.q.shape[0]
    n = x0.shape[1]

    def rhs(stage, s):
        z, D = s
        (a,) = stage
        kv = gauss_gemm(z, x, kp.sigma_v)
        v = kv @ a
        kax = _kouter(kv, a, x)
        dv = (kax - v[:, :, None] * z[:, None, :]) / kp.sigma_v**2
        return (v, jnp.einsum("bij,bjk->bik", dv, D))

    step = _rk4_with_stages(None, rhs, n_steps)
    D0 = jnp.broadcast_to(jnp.eye(n), (x0.shape[0], n, n))
    (z1, D1), _ = jax.lax.scan(step, (x0, D0), (sd.a,))
    return z1, jnp.linalg.det(D1)


def data_cost(
    P0: jnp.ndarray,
    q0: jnp.ndarray,
    J0: jnp.ndarray,
    x: jnp.ndarray,
    y: jnp.ndarray,
    kp: KernelParams,
    sigma: float,
    n_steps: int,
    div_term: bool = False,
) -> jnp.ndarray:
    """Cost (27): H(P0) + 1/(2 sigma^2) sum_i |k_1(x_i) - y_i|^2."""
    s0 = State(q0, J0, P0)
    final = shoot(s0, x, kp, n_steps, div_term=div_term)
    r = final.q - y
    return hamiltonian(s0, x, kp) + 0.5 * jnp.sum(r * r) / sigma**2


def evaluate_lagrangian(
    xi: jnp.ndarray,
    k0_batch: Callable[[jnp.ndarray], jnp.ndarray],
    x: jnp.ndarray,
    sd: StageData,
    kp: KernelParams,
    f32: bool = False,
) -> jnp.ndarray:
    """k_1(xi) = psi_1(k0(phi_1^-1(xi))) by the two Lagrangian flows (no Dk0, no field gradients).

    phi_1^-1(xi): the flow of v_t integrated backwards from t = 1 to 0 (the recorded RK4 stages
    in reverse order); psi_1: the flow of w_t forwards. Mathematically the same map as eq. (29)
    (k_t = psi_t o k0 o phi_t^-1), numerically a different discretisation: its deviation from
    `evolve_kinematics` is measured by LddmmModel.tune_evaluation, not assumed.
    `k0_batch`: (B, n) -> (B, m). f32 as in evolve_kinematics (displacements in float32 on
    coordinates centred on the landmarks).
    """
    n_steps = sd.q.shape[0]
    dt = jnp.float32 if f32 else xi.dtype
    cx = jnp.mean(x, axis=0)
    cy = jnp.mean(sd.q[0, 0], axis=0)
    sv = jnp.asarray(kp.sigma_v, dtype=dt)
    sw = jnp.asarray(kp.sigma_w, dtype=dt)
    x_c = (x - cx).astype(dt)
    xi_c = (xi - cx).astype(dt)
    h = 1.0 / n_steps

    def v_at(z_c, a):
        return gauss_gemm(z_c, x_c, sv) @ a

    def back_step(u, a4):  # a4 (4, N, n): stages (t, t+h/2, t+h/2, t+h) of one forward step
        z = xi_c + u
        k1 = v_at(z, a4[3])  # RK4 for dz/dt = v_t(z), stepping from t + h back to t
        k2 = v_at(z - 0.5 * h * k1, a4[2])
        k3 = v_at(z - 0.5 * h * k2, a4[1])
        k4 = v_at(z - h * k3, a4[0])
        return u - (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4), None

    u_x, _ = jax.lax.scan(back_step, jnp.zeros_like(xi_c), sd.a.astype(dt)[::-1])
    z = xi + u_x.astype(xi.dtype)
    y0 = k0_batch(z)
    y0_c = (y0 - cy).astype(dt)
    sq = (sd.q - cy).astype(dt)
    sb = sd.b.astype(dt)

    def fwd_step(u, st):
        q4, b4 = st

        def w_at(uu, r):
            return gauss_gemm(y0_c + uu, q4[r], sw) @ b4[r]

        k1 = w_at(u, 0)
        k2 = w_at(u + 0.5 * h * k1, 1)
        k3 = w_at(u + 0.5 * h * k2, 2)
        k4 = w_at(u + h * k3, 3)
        return u + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4), None

    u_y, _ = jax.lax.scan(fwd_step, jnp.zeros_like(y0_c), (sq, sb))
    return y0 + u_y.astype(y0.dtype)
