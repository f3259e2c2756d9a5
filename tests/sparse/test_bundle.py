"""Bundle adjustment against a synthetic affine scene with known cameras, points and noise."""

from __future__ import annotations

import numpy as np

from recon_core.geometry import affine
from recon_core.sparse.bundle import bundle_adjust


def test_bundle_adjustment_recovers_noise_level():
    rng = np.random.default_rng(3)
    n, T = 400, 4
    X = rng.uniform([-500, -500, 0], [500, 500, 40], (n, 3))
    cams = np.stack([np.hstack([rng.normal(0, 1, (2, 3)) + [[1, 0, 0], [0, 1, 0.3 * k]], [[500], [500]]])
                     for k in range(T)])
    cam_idx = np.repeat(np.arange(T), n)
    pt_idx = np.tile(np.arange(n), T)
    xy = affine.project(cams, X).reshape(-1, 2) + rng.normal(0, 0.3, (T * n, 2))
    fixed = np.zeros((T, 2, 4), bool)
    fixed[0] = True
    fixed[1, 0] = True                    # 12 gauge entries
    start = cams + rng.normal(0, 1e-3, cams.shape) * [1, 1, 1, 100]
    start[fixed] = cams[fixed]
    X0 = X + rng.normal(0, 2.0, X.shape)
    res = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(T), np.arange(n), fixed, loss="linear")
    assert res.cost_after < res.cost_before
    assert res.rms_px < 0.45                     # ~ sqrt(5/8) * 0.3 * sqrt(2) at the optimum
    assert np.array_equal(res.cams[fixed], cams[fixed])
    assert np.abs(res.X - X).max() < 3.0


def test_robust_loss_resists_gross_outliers():
    """With 5 % of the observations off by 30 px, the Huber loss keeps the structure close to
    the truth where least squares is dragged away."""
    rng = np.random.default_rng(5)
    n, T = 300, 4
    X = rng.uniform([-500, -500, 0], [500, 500, 40], (n, 3))
    cams = np.stack([np.hstack([rng.normal(0, 1, (2, 3)) + [[1, 0, 0], [0, 1, 0.3 * k]], [[500], [500]]])
                     for k in range(T)])
    cam_idx, pt_idx = np.repeat(np.arange(T), n), np.tile(np.arange(n), T)
    xy = affine.project(cams, X).reshape(-1, 2) + rng.normal(0, 0.3, (T * n, 2))
    bad = rng.choice(T * n, T * n // 20, replace=False)
    xy[bad] += rng.choice([-30.0, 30.0], (len(bad), 2))
    fixed = np.zeros((T, 2, 4), bool)
    fixed[0] = True
    fixed[1, 0] = True
    errs = {}
    for loss in ("linear", "huber"):
        res = bundle_adjust(cams.copy(), X.copy(), cam_idx, pt_idx, xy, np.arange(T), np.arange(n),
                            fixed, loss=loss, f_scale=1.0)
        errs[loss] = np.median(np.linalg.norm(res.X - X, axis=1))
    assert errs["huber"] < 0.5 * errs["linear"]



def test_compiled_assembly_takes_the_same_steps_as_the_sparse_path():
    """The compiled per-point normal equations are the same equations: same iterations, same
    cost to 1e-12, same parameters to 1e-7 (a gauge-fixed problem with a Huber loss)."""
    rng = np.random.default_rng(3)
    n, T = 600, 8
    X, cams, cam_idx, pt_idx = _random_scene(rng, n, T, 0.5)
    xy, fixed, start, X0 = _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, 2.0)
    xy[::50] += 8.0                                                   # outliers: Huber weights
    free_pts = np.arange(0, n, 2)                                      # some points held
    a = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, T), free_pts, fixed, compiled=True)
    b = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, T), free_pts, fixed, compiled=False)
    assert a.iterations == b.iterations > 2
    assert abs(a.cost_after - b.cost_after) <= 1e-12 * b.cost_after
    assert np.abs(a.cams - b.cams).max() < 1e-7 and np.abs(a.X - b.X).max() < 1e-7
    assert np.array_equal(a.X[1::2], X0[1::2]) and np.array_equal(a.cams[0], start[0])


def test_a_local_adjustment_compiled_takes_the_sparse_paths_steps():
    """A local adjustment: 2 of 10 cameras free with the points they see, most of those
    points' observations in held cameras (the compiled Schur pass leaves those out)."""
    rng = np.random.default_rng(8)
    n, T = 500, 10
    X, cams, cam_idx, pt_idx = _random_scene(rng, n, T, 0.6)
    xy, fixed, start, X0 = _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, 2.0)
    free_cams = np.array([4, 7])
    free_pts = np.unique(pt_idx[np.isin(cam_idx, free_cams)])
    a = bundle_adjust(start, X0, cam_idx, pt_idx, xy, free_cams, free_pts, fixed, compiled=True)
    b = bundle_adjust(start, X0, cam_idx, pt_idx, xy, free_cams, free_pts, fixed, compiled=False)
    assert a.iterations == b.iterations > 2
    assert abs(a.cost_after - b.cost_after) <= 1e-12 * b.cost_after
    assert np.abs(a.cams - b.cams).max() < 1e-7 and np.abs(a.X - b.X).max() < 1e-7
    held = np.setdiff1d(np.arange(T), free_cams)
    assert np.array_equal(a.cams[held], start[held])


def test_a_looser_tolerance_stops_earlier_near_the_same_cost():
    """rel_tol: the adjustment stops once an iteration gains less than that fraction of the
    cost; a growing model's adjustments use 1e-5, the final ones 1e-6."""
    rng = np.random.default_rng(4)
    n, T = 600, 8
    X, cams, cam_idx, pt_idx = _random_scene(rng, n, T, 0.5)
    xy, fixed, start, X0 = _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, 2.0)
    xy[::40] += 6.0                                                   # Huber: slower convergence
    args = (start, X0, cam_idx, pt_idx, xy, np.arange(1, T), np.arange(n), fixed)
    tight = bundle_adjust(*args, rel_tol=1e-6)
    loose = bundle_adjust(*args, rel_tol=1e-2)
    assert loose.iterations < tight.iterations
    assert tight.cost_after <= loose.cost_after <= 1.02 * tight.cost_after


def _random_scene(rng, n, T, seen):
    """n points over 1 km x 1 km x 40 m, T affine cameras, each point seen by each camera with
    probability `seen`: (X, cams, cam_idx, pt_idx)."""
    X = rng.uniform([-500, -500, 0], [500, 500, 40], (n, 3))
    cams = np.stack([np.hstack([rng.normal(0, 1, (2, 3)) + [[1, 0, 0], [0, 1, 0.3 * k]], [[500], [500]]])
                     for k in range(T)])
    cam_idx, pt_idx = np.nonzero(rng.uniform(size=(T, n)) < seen)
    return X, cams, cam_idx, pt_idx


def _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, point_noise, pixel_noise=0.3):
    """Noisy observations of (cams, X) and a start away from them with the pipeline's gauge
    (camera 0 and row 0 of camera 1 held): (xy, fixed, start cameras, start points)."""
    T = len(cams)
    xy = affine.project(cams, X)[cam_idx, pt_idx] + rng.normal(0, pixel_noise, (len(cam_idx), 2))
    fixed = np.zeros((T, 2, 4), bool)
    fixed[0] = True
    fixed[1, 0] = True
    start = cams + rng.normal(0, 1e-3, cams.shape) * [1, 1, 1, 100]
    start[fixed] = cams[fixed]
    return xy, fixed, start, X + rng.normal(0, point_noise, X.shape)


def test_compiled_schur_with_a_point_seen_twice_by_one_camera():
    """The compiled Schur complement files each pair of observations once in the upper triangle;
    a point observed twice by one camera (an inconsistent track) must still give the sparse
    path's equations."""
    rng = np.random.default_rng(5)
    n, T = 300, 5
    X, cams, cam_idx, pt_idx = _random_scene(rng, n, T, 0.6)
    dup = np.flatnonzero(cam_idx >= 2)[::7]
    cam_idx, pt_idx = np.r_[cam_idx, cam_idx[dup]], np.r_[pt_idx, pt_idx[dup]]
    xy, fixed, start, X0 = _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, 2.0)
    a = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, T), np.arange(n), fixed, compiled=True)
    b = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, T), np.arange(n), fixed, compiled=False)
    c = bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, T), np.arange(n), fixed, solver="sparse")
    assert abs(c.cost_after - b.cost_after) <= 1e-9 * b.cost_after and c.iterations == b.iterations
    assert a.iterations == b.iterations > 2
    assert abs(a.cost_after - b.cost_after) <= 1e-12 * b.cost_after
    assert np.abs(a.cams - b.cams).max() < 1e-7 and np.abs(a.X - b.X).max() < 1e-7


def _strip_problem(rng, T=24, per=120):
    """Tiles along a strip: point block k is seen by cameras k - 1, k, k + 1 (S block
    tridiagonal), gauge held as the SfM holds it."""
    cams = np.stack([np.hstack([rng.normal(0, 0.05, (2, 3)) + [[1, 0, 0], [0, 1, 0.2 * (k % 3)]],
                                [[500.0], [500.0]]]) for k in range(T)])
    X = np.concatenate([rng.uniform([60 * k, 0, 0], [60 * k + 100, 100, 30], (per, 3)) for k in range(T)])
    cam_idx = np.concatenate([np.repeat(c, per) for k in range(T) for c in range(max(0, k - 1), min(T, k + 2))])
    pt_idx = np.concatenate([np.arange(per) + per * k for k in range(T) for c in range(max(0, k - 1), min(T, k + 2))])
    xy, fixed, start, X0 = _gauge_fixed_start(rng, cams, X, cam_idx, pt_idx, 1.0, pixel_noise=0.2)
    return start, X0, cam_idx, pt_idx, xy, fixed


def test_the_block_sparse_system_takes_the_same_steps_as_the_dense_one(monkeypatch):
    """Large sites take the block-sparse reduced system (solver="sparse", SuperLU): on a strip
    of tiles, with held gauge entries, it takes the dense Cholesky's steps; "auto" takes it from
    bundle.SPARSE_SOLVE_MIN unknowns."""
    import recon_core.sparse.ba_kernels as kern
    import recon_core.sparse.bundle as bundle

    rng = np.random.default_rng(11)
    start, X0, cam_idx, pt_idx, xy, fixed = _strip_problem(rng)
    T = len(start)
    args = (start, X0, cam_idx, pt_idx, xy, np.arange(1, T), np.arange(len(X0)), fixed)
    dense = bundle_adjust(*args, solver="dense")
    sparse = bundle_adjust(*args, solver="sparse")
    assert sparse.iterations == dense.iterations > 2
    assert abs(sparse.cost_after - dense.cost_after) <= 1e-9 * dense.cost_after
    assert np.abs(sparse.cams - dense.cams).max() < 1e-6 and np.abs(sparse.X - dense.X).max() < 1e-5
    assert np.array_equal(sparse.cams[fixed], start[fixed])

    calls, orig = [], kern.schur_blocks

    def counting(*a):
        calls.append(1)
        return orig(*a)

    monkeypatch.setattr(kern, "schur_blocks", counting)
    bundle_adjust(*args, max_nfev=1)
    assert not calls                                   # 180 unknowns: dense
    monkeypatch.setattr(bundle, "SPARSE_SOLVE_MIN", 100)
    auto = bundle_adjust(*args)
    assert calls and auto.cost_after == sparse.cost_after


def test_a_local_adjustment_on_the_block_sparse_system(monkeypatch):
    """Held cameras (a local adjustment) and a factorisation that turns dense when SuperLU fills
    (bundle.DENSE_FILL): the same steps as the dense system."""
    import recon_core.sparse.bundle as bundle

    rng = np.random.default_rng(12)
    start, X0, cam_idx, pt_idx, xy, fixed = _strip_problem(rng, T=16)
    free_cams = np.arange(5, 12)
    free_pts = np.unique(pt_idx[np.isin(cam_idx, free_cams)])
    args = (start, X0, cam_idx, pt_idx, xy, free_cams, free_pts, fixed)
    dense = bundle_adjust(*args, solver="dense")
    for fill in (0.4, 0.0):                            # SuperLU throughout; dense after the first
        monkeypatch.setattr(bundle, "DENSE_FILL", fill)
        sparse = bundle_adjust(*args, solver="sparse")
        assert sparse.iterations == dense.iterations > 2
        assert abs(sparse.cost_after - dense.cost_after) <= 1e-9 * dense.cost_after
        assert np.abs(sparse.cams - dense.cams).max() < 1e-6
        held = np.setdiff1d(np.arange(len(start)), free_cams)
        assert np.array_equal(sparse.cams[held], start[held])


def test_block_pattern_is_the_set_of_cameras_sharing_a_point():
    """The symbolic pass against brute force: block (a, b), a <= b, exists iff some point is
    seen by both compact cameras (or a == b)."""
    from recon_core.sparse.ba_kernels import block_pattern

    rng = np.random.default_rng(4)
    T, npt = 30, 200
    obs = [(c, p) for p in range(npt) for c in rng.choice(T, rng.integers(1, 5), replace=False)]
    oc = np.array([o[0] for o in obs], np.int64)
    op = np.array([o[1] for o in obs], np.int64)
    cc = np.arange(T, dtype=np.int64)
    cc[[3, 17]] = -1                                   # held cameras: not in the system
    cc[cc >= 0] = np.arange(T - 2)
    keep = cc[oc] >= 0
    order = np.flatnonzero(keep)[np.argsort(op[keep], kind="stable")]
    start = np.searchsorted(op[order], np.arange(npt + 1)).astype(np.int64)
    bptr, bcol = block_pattern(oc, cc, T - 2, order, start)
    got = {(a, int(b)) for a in range(T - 2) for b in bcol[bptr[a]:bptr[a + 1]]}
    want = {(a, a) for a in range(T - 2)}
    for p in range(npt):
        cs = sorted({int(cc[c]) for c in oc[op == p] if cc[c] >= 0})
        want |= {(x, y) for i, x in enumerate(cs) for y in cs[i:]}
    assert got == want
    assert all(np.all(np.diff(bcol[bptr[a]:bptr[a + 1]]) > 0) for a in range(T - 2))


def test_the_kernel_warmup_compiles_the_signatures_the_sfm_uses(tiny_run):
    """A first `aerec view` compiles the BA kernels ahead on a toy problem: the SfM (run by the
    tiny_run fixture in this process) must have called them with the same argument types, or
    the warm-up compiles signatures nobody uses."""
    from recon_core.sparse import ba_kernels as kern
    from recon_core.sparse.bundle import warm_compiled_kernels

    used = {f: set(getattr(kern, f).signatures) for f in ("assemble_blocks", "schur", "back_substitute")}
    assert all(used.values()), used
    warm_compiled_kernels()
    assert {f: set(getattr(kern, f).signatures) for f in used} == used


def test_dissection_orders_a_grid_of_tiles_separators_last():
    """The factorisation's order (bundle._dissection_order) on a 24 x 24 grid of tiles, each
    coupled to its 8 neighbours: a permutation of all cameras, whose last cameras (the first
    separator) split the rest into two sides with no coupling between them, and whose fill in
    SuperLU is far below the natural order's."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import splu

    from recon_core.sparse.bundle import _dissection_order

    g = 24
    ij = np.array([(i, j) for i in range(g) for j in range(g)])
    pairs = {(a, b) for a in range(g * g) for b in range(g * g)
             if a <= b and np.abs(ij[a] - ij[b]).max() <= 1}
    rows = sorted(pairs)
    bptr = np.searchsorted([r[0] for r in rows], np.arange(g * g + 1)).astype(np.int64)
    bcol = np.array([r[1] for r in rows], np.int64)
    order = _dissection_order(bptr, bcol, ij.astype(float), leaf=4)
    assert sorted(order.tolist()) == list(range(g * g))
    # the top separator: the cameras emitted last that touch both remaining sides
    sep = set(order[-g:].tolist())
    rest = [a for a in order[:-g]]
    side = {a: ij[a][0] < g / 2 for a in rest}
    for a, b in pairs:
        if a in side and b in side:
            assert side[a] == side[b]             # no coupling across the separator
    A = coo_matrix((np.ones(len(rows)), (bptr.searchsorted(np.arange(len(rows)), "right") - 1, bcol)),
                   shape=(g * g, g * g)).toarray()
    A = A + A.T + 20 * np.eye(g * g)
    inv = np.empty_like(order)
    inv[order] = np.arange(len(order))

    def fill(P):
        from scipy.sparse import csc_matrix
        lu = splu(csc_matrix(A[np.ix_(P, P)]), permc_spec="NATURAL",
                  options={"SymmetricMode": True, "DiagPivotThresh": 0.0})
        return lu.L.nnz + lu.U.nnz
    assert len(sep) == g
    assert fill(order) < 0.8 * fill(np.arange(g * g))


def test_the_block_system_refuses_the_uncompiled_path():
    """solver="sparse" needs the compiled kernels: asked for with compiled=False, a clear error,
    not a silent dense solve."""
    import pytest

    rng = np.random.default_rng(13)
    start, X0, cam_idx, pt_idx, xy, fixed = _strip_problem(rng, T=4, per=20)
    with pytest.raises(ValueError, match="compiled"):
        bundle_adjust(start, X0, cam_idx, pt_idx, xy, np.arange(1, 4), np.arange(len(X0)), fixed,
                      solver="sparse", compiled=False)
