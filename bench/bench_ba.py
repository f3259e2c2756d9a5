"""Bundle adjustment on one global problem: this project's solver (compiled per-point assembly
and the scipy.sparse path) against Ceres (pyceres, same Huber objective), same start.

The problem is a group's saved affine model (OUT/affine/group_<k>), cameras and points moved
away from the optimum by a seeded perturbation (points by `--noise` frame units, camera
offsets by the same in pixels), the gauge entries held as the pipeline holds them. Prints
time, iterations and final robust cost for each solver; Ceres' time is also split into its
own solver time and the evaluation of the residuals and Jacobians (done here by a Python cost
function, which no C++ user of Ceres would pay).

Our solver runs twice: with the reduced camera system dense (Cholesky) and block-sparse (the
`solver="sparse"` path large sites take).

    python bench/bench_ba.py OUT [--group 0] [--noise 1.0] [--repeat 3]
    (OUT: e.g. /tmp/aerec_bench/out_demo_s0 after bench_pipeline.py --preset demo)
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.io.models import load_model  # noqa: E402
from recon_core.sparse.bundle import _robust, bundle_adjust  # noqa: E402


def problem(out: Path, group: int, noise: float, seed: int = 0):
    if group < 0:                    # every group of a joint run, merged back into one model
        from recon_core.io.layout import OutLayout
        from recon_core.model.sparse_model import merge_joint

        m = merge_joint([load_model(out, g) for g in OutLayout(out).model_groups()])
        if m is None:
            sys.exit(f"{out}: its groups are not one joint reconstruction")
    else:
        m = load_model(out, group)
    idx = m.active_obs()
    o = m.obs
    rng = np.random.default_rng(seed)
    cams = m.cams.copy()
    X = m.X.copy()
    ids = m.point_ids()
    X[ids] += rng.normal(0, noise, (len(ids), 3))
    free = np.flatnonzero(m.registered)
    cams[free, :, 3] += np.where(m.fixed[free, :, 3], 0.0, rng.normal(0, noise, (len(free), 2)))
    return dict(cams=cams, X=X, oc=o.tile[idx], op=o.track[idx], xy=o.xy[idx], free_cams=free,
                free_pts=ids, fixed=m.fixed.copy())


def robust_cost(pr, cams, X) -> float:
    r = np.einsum("kij,kj->ki", cams[pr["oc"], :, :3], X[pr["op"]]) + cams[pr["oc"], :, 3] - pr["xy"]
    return 0.5 * float(_robust(np.sum(r * r, axis=1), "huber", 1.0)[0].sum())


def run_ours(pr, compiled: bool, solver: str = "dense"):
    t0 = time.perf_counter()
    res = bundle_adjust(pr["cams"], pr["X"], pr["oc"], pr["op"], pr["xy"], pr["free_cams"],
                        pr["free_pts"], pr["fixed"], loss="huber", f_scale=1.0, max_nfev=50,
                        compiled=compiled, solver=solver)
    return time.perf_counter() - t0, res.iterations, robust_cost(pr, res.cams, res.X)


def run_ceres(pr):
    import pyceres

    class Reprojection(pyceres.CostFunction):
        def __init__(self, x):
            super().__init__()
            self.x = x
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([8, 3])

        def Evaluate(self, params, residuals, jacobians):
            P = params[0].reshape(2, 4)
            Xp = params[1]
            residuals[:] = P[:, :3] @ Xp + P[:, 3] - self.x
            if jacobians is not None:
                if jacobians[0] is not None:
                    J = np.zeros((2, 8))
                    J[0, :3] = J[1, 4:7] = Xp
                    J[0, 3] = J[1, 7] = 1.0
                    jacobians[0][:] = J.ravel()
                if jacobians[1] is not None:
                    jacobians[1][:] = P[:, :3].ravel()
            return True

    cams = pr["cams"].reshape(len(pr["cams"]), 8).copy()
    X = pr["X"].copy()
    prob = pyceres.Problem()
    loss = pyceres.HuberLoss(1.0)
    free_c = set(pr["free_cams"].tolist())
    free_p = set(pr["free_pts"].tolist())
    use = np.array([c in free_c or p in free_p for c, p in zip(pr["oc"], pr["op"])])
    for k in np.flatnonzero(use):
        c, p = int(pr["oc"][k]), int(pr["op"][k])
        prob.add_residual_block(Reprojection(pr["xy"][k].copy()), loss, [cams[c], X[p]])
    for c in set(pr["oc"][use].tolist()):
        fx = pr["fixed"][c].ravel()
        if c not in free_c or fx.all():
            prob.set_parameter_block_constant(cams[c])
        elif fx.any():
            prob.set_manifold(cams[c], pyceres.SubsetManifold(8, np.flatnonzero(fx).tolist()))
    for p in set(pr["op"][use].tolist()):
        if p not in free_p:
            prob.set_parameter_block_constant(X[p])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = pyceres.LinearSolverType.DENSE_SCHUR
    opts.minimizer_progress_to_stdout = False
    opts.max_num_iterations = 50
    opts.function_tolerance = 1e-6
    opts.num_threads = 2
    summ = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(opts, prob, summ)
    wall = time.perf_counter() - t0
    evaluation = summ.residual_evaluation_time_in_seconds + summ.jacobian_evaluation_time_in_seconds
    return (wall, summ.num_successful_steps + summ.num_unsuccessful_steps, summ.final_cost,
            summ.total_time_in_seconds - evaluation, summ.linear_solver_time_in_seconds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--group", type=int, default=0)
    ap.add_argument("--noise", type=float, default=1.0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--joint", action="store_true", help="all groups of a joint run as one problem")
    ap.add_argument("--only-compiled", action="store_true", help="neither the scipy.sparse path nor Ceres")
    a = ap.parse_args()
    if a.joint:
        a.group = -1
    pr = problem(a.out, a.group, a.noise)
    n_cam = len(pr["free_cams"])
    print(f"global problem of {a.out} group {a.group}: {n_cam} tile cameras, {len(pr['free_pts'])} points, "
          f"{len(pr['oc'])} observations; start cost {robust_cost(pr, pr['cams'], pr['X']):.1f}")
    run_ours(pr, True)                                        # compile (cached on disk after)
    run_ours(pr, True, "sparse")
    for name, compiled, solver in (("aerec, compiled, dense S", True, "dense"),
                                   ("aerec, compiled, block-sparse S", True, "sparse"),
                                   ("aerec, scipy.sparse assembly", False, "dense"))[:2 if a.only_compiled else 3]:
        runs = [run_ours(pr, compiled, solver) for _ in range(a.repeat)]
        t = sorted(r[0] for r in runs)
        print(f"{name:30s} time min/median {t[0]:7.3f} / {t[len(t) // 2]:7.3f} s, "
              f"{runs[0][1]} iterations, final cost {runs[0][2]:.4f}")
    if a.only_compiled:
        return
    try:
        import pyceres  # noqa: F401
    except ImportError as exc:
        print(f"pyceres not importable ({exc}): `pip install pyceres` to compare with Ceres")
        return
    runs = [run_ceres(pr) for _ in range(a.repeat)]
    best = min(runs, key=lambda r: r[0])
    print(f"{'Ceres (pyceres), DENSE_SCHUR':30s} time min {best[0]:7.3f} s (solver without the Python "
          f"cost evaluation {best[3]:.3f} s, of which linear solver {best[4]:.3f} s), "
          f"{best[1]} iterations, final cost {best[2]:.4f}")


if __name__ == "__main__":
    main()
