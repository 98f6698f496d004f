"""`workcell bench lddmm-pendulum`: reproduce section 4 of Orozco & Ratajczak (double pendulum).

Nominal kinematics (eq. 30), l1 = 1 m, l2 = 0.5 m, planar, y = (horizontal, vertical):
    k0(x) = (l1 cos x1 + l2 cos(x1+x2),  l1 sin x1 + l2 sin(x1+x2)).
Joint ranges: x1, x2 in [-pi, pi] (the whole annulus, both elbow branches and both singular
lines x2 = 0, x2 = +-pi). Training: the 13 x 13 grid over those ranges (169 points). Test:
3000 uniform random configurations in the same ranges (seed 1).

Truths:
 (a) link_lengths: l1 = 0.98, l2 = 0.53.
 (b) bending: static gravitational bending of elastic links - the static limit of Book's massless
     elastic chain, written as Euler-Bernoulli cantilevers in small deflection. Gravity g = 9.81
     m/s^2 along -y. Link i has absolute angle a_i (a1 = x1, a2 = x1 + x2), unit vectors
     e_i = (cos a_i, sin a_i), n_i = (-sin a_i, cos a_i), weight per length mu_i g (mu = 2 kg/m
     both), bending stiffness EI = 1000 N m^2 both, tip payload m_p = 1 kg. Loads normal to a
     link (sign along n_i): distributed p_i = -mu_i g cos a_i; link 2 tip force F2 = -m_p g cos a2;
     link 1 tip force F1 = -(mu_2 l2 + m_p) g cos a1 and tip moment
     M1 = -(mu_2 g l2^2/2 + m_p g l2) cos a2 (weight of the outer link about joint 2). Cantilever
     tip deflection / slope: d = p L^4/(8EI) + F L^3/(3EI) + M L^2/(2EI),
     s = p L^3/(6EI) + F L^2/(2EI) + M L/EI. Then
     p1 = l1 e1 + d1 n1;  a2' = a2 + s1;  y = p1 + l2 e(a2') + d2 n(a2').
     (max tip error ~ 1.5 cm).
 (c) diffeomorphism: the paper's formula is garbled in our copy, so a documented equivalent: the
     nonlinear shear y' = S2(S1(k0(x))) followed by t = (0.05, -0.04), with
     S1(y) = (y1 + 0.08 y2^2, y2), S2(y) = (y1, y2 - 0.06 y1^2); each S is triangular with unit
     diagonal Jacobian, hence a diffeomorphism of R^2 (errors up to ~0.2 m).

Per scenario: median / max Euclidean error on the test set before (k0) and after calibration,
reduction = median_before / median_after, fit time (including width CV), min Jacobian
determinant of phi_1 and psi_1 over the test set (reported min of both), and a heat-map PNG in
--out (like the paper's Fig. 3: test points in task space coloured by log10 error).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time

import numpy as np

from workcell._jax import jnp
from workcell.atomic import save_figure, write_text
from workcell.bench import check_bench_outputs, environment
from workcell.errors import OneLineParser, UserError, check_output_path

L1, L2 = 1.0, 0.5
G = 9.81
MU = 2.0  # kg/m
EI = 1000.0  # N m^2
M_P = 1.0  # kg
SHIFT = np.array([0.05, -0.04])
RANGE = (-math.pi, math.pi)


def k0(x: jnp.ndarray) -> jnp.ndarray:
    """Nominal double pendulum (eq. 30), JAX."""
    return jnp.array(
        [
            L1 * jnp.cos(x[0]) + L2 * jnp.cos(x[0] + x[1]),
            L1 * jnp.sin(x[0]) + L2 * jnp.sin(x[0] + x[1]),
        ]
    )


def fk_np(x: np.ndarray, l1: float = L1, l2: float = L2) -> np.ndarray:
    a1, a2 = x[:, 0], x[:, 0] + x[:, 1]
    return np.stack([l1 * np.cos(a1) + l2 * np.cos(a2), l1 * np.sin(a1) + l2 * np.sin(a2)], 1)


def truth_link_lengths(x: np.ndarray) -> np.ndarray:
    return fk_np(x, 0.98, 0.53)


def _cantilever(p, F, M, L):
    d = p * L**4 / (8 * EI) + F * L**3 / (3 * EI) + M * L**2 / (2 * EI)
    s = p * L**3 / (6 * EI) + F * L**2 / (2 * EI) + M * L / EI
    return d, s


def truth_bending(x: np.ndarray) -> np.ndarray:
    a1, a2 = x[:, 0], x[:, 0] + x[:, 1]
    c1, c2 = np.cos(a1), np.cos(a2)
    p1, p2 = -MU * G * c1, -MU * G * c2
    F2 = -M_P * G * c2
    F1 = -(MU * L2 + M_P) * G * c1
    M1 = -(MU * G * L2**2 / 2 + M_P * G * L2) * c2
    d1, s1 = _cantilever(p1, F1, M1, L1)
    d2, _ = _cantilever(p2, F2, 0.0, L2)

    def e(a):
        return np.stack([np.cos(a), np.sin(a)], 1)

    def n(a):
        return np.stack([-np.sin(a), np.cos(a)], 1)

    a2b = a2 + s1
    return L1 * e(a1) + d1[:, None] * n(a1) + L2 * e(a2b) + d2[:, None] * n(a2b)


def truth_diffeo(x: np.ndarray) -> np.ndarray:
    y = fk_np(x)
    y1 = y[:, 0] + 0.08 * y[:, 1] ** 2
    y2 = y[:, 1] - 0.06 * y1**2
    return np.stack([y1, y2], 1) + SHIFT


SCENARIOS = {
    "link_lengths": truth_link_lengths,
    "bending": truth_bending,
    "diffeomorphism": truth_diffeo,
}


def datasets(n_grid: int = 13, n_test: int = 3000, seed: int = 1):
    g = np.linspace(*RANGE, n_grid)
    X_train = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    X_test = np.random.default_rng(seed).uniform(*RANGE, size=(n_test, 2))
    return X_train, X_test


def _heatmaps(path: str, rows: list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(rows), 2, figsize=(9, 4.2 * len(rows)), squeeze=False)
    for r, (name, Yt, eb, ea) in enumerate(rows):
        lo = math.floor(np.log10(max(min(eb.min(), ea.min()), 1e-9)))
        hi = math.ceil(np.log10(max(eb.max(), ea.max())))
        for c, (err, title) in enumerate(((eb, "before"), (ea, "after"))):
            ax = axes[r, c]
            sc = ax.scatter(
                Yt[:, 0], Yt[:, 1], c=np.log10(err), s=4, cmap="viridis", vmin=lo, vmax=hi
            )
            ax.set_aspect("equal")
            ax.set_title(f"{name}: {title} (median {np.median(err) * 1e3:.3g} mm)")
            ax.set_xlabel("y1 [m]")
            ax.set_ylabel("y2 [m]")
            fig.colorbar(sc, ax=ax, label="log10 |error| [m]")
    fig.tight_layout()
    save_figure(fig, path, dpi=110)
    plt.close(fig)


def run_scenarios(
    names=None,
    *,
    sigma: float = 1e-3,
    n_steps: int = 10,
    max_iter: int = 200,
    verbose: bool = False,
) -> dict:
    from workcell.estimation.lddmm import fit_lddmm

    X_train, X_test = datasets()
    out = {}
    for name in names or SCENARIOS:
        truth = SCENARIOS[name]
        Y_train, Y_test = truth(X_train), truth(X_test)
        t0 = time.perf_counter()
        model = fit_lddmm(
            k0, X_train, Y_train, sigma=sigma, n_steps=n_steps, max_iter=max_iter, verbose=verbose
        )
        fit_s = time.perf_counter() - t0
        pred = model.predict(X_test)
        eb = np.linalg.norm(fk_np(X_test) - Y_test, axis=1)
        ea = np.linalg.norm(pred - Y_test, axis=1)
        dphi, dpsi = model.min_jacobian_det(X_test)
        out[name] = {
            "median_before_m": float(np.median(eb)),
            "median_after_m": float(np.median(ea)),
            "max_before_m": float(eb.max()),
            "max_after_m": float(ea.max()),
            "reduction": float(np.median(eb) / np.median(ea)),
            "fit_seconds": fit_s,
            "min_jacobian_det": float(min(dphi, dpsi)),
            "min_jacobian_det_phi": dphi,
            "min_jacobian_det_psi": dpsi,
            "sigma_v": model.kp.sigma_v,
            "sigma_w": model.kp.sigma_w,
            "lbfgs_iterations": model.info.n_iter,
            "_arrays": (Y_test, eb, ea),
        }
    return out


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="workcell bench lddmm-pendulum", description=__doc__.split("\n")[0])
    ap.add_argument("--json", action="store_true", help="print one JSON object on stdout")
    ap.add_argument(
        "--out",
        default=os.path.join("out", "bench-lddmm-pendulum"),
        help="directory for the heat-map PNG and the JSON file",
    )
    ap.add_argument(
        "--force",
        action="store_true",
        help="replace heatmaps.png / results.json in --out that are not an earlier result of "
        "this bench",
    )
    ap.add_argument(
        "--scenario",
        action="append",
        choices=list(SCENARIOS),
        help="run only this scenario (repeatable)",
    )
    ap.add_argument("--sigma", type=float, default=0.1, help="data weight of cost (27)")
    ap.add_argument("--n-steps", type=int, default=10, help="RK4 steps")
    ap.add_argument("--max-iter", type=int, default=100, help="L-BFGS iterations")
    args = ap.parse_args(argv)
    if not (math.isfinite(args.sigma) and 1e-4 <= args.sigma <= 1e4):
        raise UserError(f"--sigma must be a number from 1e-4 to 1e4, got {args.sigma:g}")
    for opt, v, hi in (("--n-steps", args.n_steps, 1000), ("--max-iter", args.max_iter, 100000)):
        if not 1 <= v <= hi:
            raise UserError(f"{opt} must be 1..{hi}, got {v}")
    check_output_path(args.out, "bench output folder", folder=True)
    outs = [os.path.join(args.out, n) for n in ("heatmaps.png", "results.json")]
    for p in outs:  # never over a recording or a device
        check_output_path(p, "bench output")
    # nor over files that are not an earlier run's (unless --force)
    check_bench_outputs(
        outs,
        "lddmm-pendulum",
        outs[1],
        force=args.force,
        say=lambda m: print(m, file=sys.stderr if args.json else sys.stdout),
    )
    res = run_scenarios(
        args.scenario,
        sigma=args.sigma,
        n_steps=args.n_steps,
        max_iter=args.max_iter,
        verbose=not args.json,
    )
    os.makedirs(args.out, exist_ok=True)
    png = os.path.join(args.out, "heatmaps.png")
    _heatmaps(png, [(k, *v["_arrays"]) for k, v in res.items()])
    scen = {k: {kk: vv for kk, vv in v.items() if kk != "_arrays"} for k, v in res.items()}
    doc = {
        "bench": "lddmm-pendulum",
        "scenarios": scen,
        "joint_ranges_rad": {"x1": list(RANGE), "x2": list(RANGE)},
        "n_train": 169,
        "n_test": 3000,
        "heatmap_png": png,
        "environment": environment(),
    }
    write_text(outs[1], json.dumps(doc, indent=2))
    if args.json:
        json.dump(doc, sys.stdout)
        sys.stdout.write("\n")
        return 0
    print(
        f"double pendulum l1={L1} l2={L2}; joints x1, x2 in [{RANGE[0]:.4f}, {RANGE[1]:.4f}] rad;"
        f" 169 train (13x13 grid), 3000 random test"
    )
    hdr = (
        f"{'scenario':<16}{'med before':>12}{'med after':>12}{'max before':>12}"
        f"{'max after':>12}{'reduction':>10}{'fit s':>8}{'min det':>9}"
    )
    print(hdr)
    for k, v in scen.items():
        print(
            f"{k:<16}{v['median_before_m'] * 1e3:>10.3f}mm{v['median_after_m'] * 1e3:>10.4f}mm"
            f"{v['max_before_m'] * 1e3:>10.3f}mm{v['max_after_m'] * 1e3:>10.4f}mm"
            f"{v['reduction']:>10.1f}{v['fit_seconds']:>8.2f}{v['min_jacobian_det']:>9.3f}"
        )
    print(f"heat maps: {png}; JSON: {os.path.join(args.out, 'results.json')}")
    return 0
