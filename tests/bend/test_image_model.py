"""The per-image pushbroom tie (recon_core.bend.image_model): its algebra against functions
known to be in or out of the model's family, its invariance to the affine gauge, and how it
enters the bundle adjustment."""

from __future__ import annotations

import numpy as np

from recon_core.bend.image_model import col_basis, image_frame, image_tie, row_basis
from recon_core.sparse.bundle import bundle_adjust


def _tiles(rng, n_side=4, pts=60, size=3000.0):
    """Sample points of n_side^2 overlapping tiles over a site (ENU-like metres, some relief)."""
    step = size / n_side
    out = []
    for i in range(n_side):
        for j in range(n_side):
            xy = rng.uniform([i * step - step / 3, j * step - step / 3],
                             [(i + 1) * step + step / 3, (j + 1) * step + step / 3], (pts, 2))
            z = rng.uniform(0, 40, pts)
            out.append(np.column_stack([xy, z]))
    return out


def _affine_fits(fn, samples):
    cams = []
    for S in samples:
        A = np.hstack([S, np.ones((len(S), 1))])
        cams.append(np.linalg.lstsq(A, fn(S), rcond=None)[0].T)
    return np.array(cams)


def _linear_camera():
    return np.array([[2.0, 0.1, 0.3, 100.0], [-0.05, 2.0, -0.6, 50.0]])


def _model_function(samples, theta_r, theta_c):
    """A function in the model's family, defined with the same normalisation as the tie."""
    P = _linear_camera()
    cams = _affine_fits(lambda S: np.hstack([S, np.ones((len(S), 1))]) @ P.T, samples)
    mean_cam, x0, xs, p0, ps = image_frame(cams, samples)

    def fn(S):
        uv = np.hstack([S, np.ones((len(S), 1))]) @ mean_cam.T
        r, c = (uv[:, 1] - p0[1]) / ps, (uv[:, 0] - p0[0]) / ps
        Xn = (S - x0) / xs
        return np.column_stack([uv[:, 0] + col_basis(Xn, r, c) @ theta_c,
                                uv[:, 1] + row_basis(Xn, r, c) @ theta_r])
    return fn


def _tie_rms(cams, samples):
    t = image_tie(cams, samples, np.arange(len(cams)), 1.0)
    return np.sqrt(2 * t.cost(cams.reshape(-1)) / (16 * len(cams)))


def test_tie_is_free_inside_the_pushbroom_family_and_costs_outside():
    rng = np.random.default_rng(0)
    samples = _tiles(rng)
    # view plane turning, pitch drift; the focal plane: a bowed line (c^2, c^3), yaw drift (r^2 c)
    theta_r = np.r_[np.zeros(4), 0.8, -0.5, 0.3, 0.6, 0.3, -0.2, 0.1]
    # 1D perspective, roll drift; the focal plane: across-track distortion (c^3), scale drift (r^2 c)
    theta_c = np.r_[np.zeros(4), 0.4, 0.7, -0.2, 0.9, -0.5, 0.25, -0.15]
    inside = _affine_fits(_model_function(samples, theta_r, theta_c), samples)
    free = _tie_rms(inside, samples)
    # (not exactly 0: the tie normalises r, c by the image's own mean camera, which the second-
    # order terms move slightly)
    assert free < 1e-4

    # a dome z += k (x^2 + y^2) seen through the cameras: not a pushbroom any more
    P = _linear_camera()

    def domed(S):
        k = 1.0 / 1500.0 ** 2                                   # 1 m at 1.5 km
        Z = S.copy()
        Z[:, 2] += k * ((S[:, 0] - 1500) ** 2 + (S[:, 1] - 1500) ** 2)
        return np.hstack([Z, np.ones((len(S), 1))]) @ P.T
    bent = _affine_fits(domed, samples)
    # (one image: the bowed line's c^2 in the row takes the dome's across-track part; what
    # several views' directions still see of it is warp_observability's)
    assert _tie_rms(bent, samples) > 10 * free


def test_tie_follows_the_affine_gauge():
    """Moving the frame by a 3D affine map G (points G X, cameras P G^-1) leaves the tie's cost
    unchanged: the model's family is closed under affine maps."""
    rng = np.random.default_rng(1)
    samples = _tiles(rng, n_side=3)
    fn = _model_function(samples, np.r_[np.zeros(4), 0.5, 0.2, -0.4, 0.3, 0.2, -0.1, 0.05],
                         np.r_[np.zeros(4), -0.3, 0.5, 0.1, 0.4, 0.2, 0.1, -0.05])
    cams = _affine_fits(fn, samples) + rng.normal(0, 1e-3, (len(samples), 2, 4))
    G = np.eye(4)
    G[:3, :3] += rng.normal(0, 0.2, (3, 3))
    G[:3, 3] = rng.normal(0, 100, 3)
    Gi = np.linalg.inv(G)
    moved_samples = [S @ G[:3, :3].T + G[:3, 3] for S in samples]
    moved = np.einsum("tij,jk->tik", cams, Gi)
    a, b = _tie_rms(cams, samples), _tie_rms(moved, moved_samples)
    assert a > 1e-5
    assert abs(a - b) < 1e-6 * max(a, 1.0) + 1e-9


def test_bundle_adjustment_honours_the_tie():
    """Observations that cannot decide between cameras (each tile sees only its own points) and
    a tie: the adjusted cameras satisfy the tie, the compiled and scipy.sparse paths agree, and
    the reported cost includes the penalty."""
    rng = np.random.default_rng(2)
    samples = _tiles(rng, n_side=3, pts=40)
    fn = _model_function(samples, np.r_[np.zeros(4), 0.5, 0.2, -0.4, 0.3, 0.2, -0.1, 0.05],
                         np.r_[np.zeros(4), -0.3, 0.5, 0.1, 0.4, 0.2, 0.1, -0.05])
    X = np.concatenate(samples)
    oc = np.repeat(np.arange(len(samples)), [len(s) for s in samples])
    op = np.arange(len(X))
    xy = fn(X) + rng.normal(0, 0.05, (len(X), 2))
    start = _affine_fits(fn, samples) + rng.normal(0, 0.02, (len(samples), 2, 4)) * [1, 1, 1, 10]
    tie = image_tie(start, samples, np.arange(len(samples)), 100.0)
    held = np.arange(0)                                        # points held: the frame is fixed
    runs = [bundle_adjust(start, X, oc, op, xy, np.arange(len(samples)), held, None, loss="linear",
                          ties=[tie], compiled=c, solver=sv) for c, sv in ((True, "dense"), (False, "dense"),
                                                                         (True, "sparse"))]
    for res in runs:
        assert res.cost_after < res.cost_before
        assert _tie_rms(res.cams, samples) < 0.5 * _tie_rms(start, samples)
    assert np.allclose(runs[0].cams, runs[1].cams, atol=1e-8)
    # the block-sparse system: the tie's low-rank part by Woodbury, the same steps
    assert runs[2].iterations == runs[0].iterations
    assert np.allclose(runs[2].cams, runs[0].cams, atol=1e-7)
    r = np.einsum("kij,kj->ki", runs[0].cams[oc, :, :3], X) + runs[0].cams[oc, :, 3] - xy
    assert runs[0].cost_after >= 0.5 * float((r ** 2).sum()) + tie.cost(runs[0].cams.reshape(-1)) - 1e-9


def test_the_factored_tie_is_the_projection_penalty():
    """Tie keeps Q = w D^T (I - Pi) D in factors (block-diagonal minus low rank); against Q built
    the plain way, with D and the projector on the model's columns as dense matrices."""
    rng = np.random.default_rng(6)
    samples = _tiles(rng, n_side=3, pts=30)
    cams = _affine_fits(lambda S: np.hstack([S, np.ones((len(S), 1))]) @ _linear_camera().T, samples)
    cams = cams + rng.normal(0, 1e-3, cams.shape)
    w = 3.0
    tie = image_tie(cams, samples, np.arange(len(cams)) + 2, w)
    n = len(cams)
    mean_cam, x0, xs, p0, ps = image_frame(cams, samples)
    Q = np.zeros((8 * n, 8 * n))
    for coord in range(2):
        Ds, Gs = [], []
        for S in samples:
            Sh = np.hstack([S, np.ones((len(S), 1))])
            uv = Sh @ mean_cam.T
            r, c = (uv[:, 1] - p0[1]) / ps, (uv[:, 0] - p0[0]) / ps
            B = col_basis((S - x0) / xs, r, c) if coord == 0 else row_basis((S - x0) / xs, r, c)
            E = Sh * np.sqrt(8.0 / len(S))
            Ds.append(E)
            Gs.append(E @ np.linalg.pinv(Sh) @ B)
        D = np.zeros((sum(len(E) for E in Ds), 4 * n))
        r0 = 0
        for t, E in enumerate(Ds):
            D[r0:r0 + len(E), 4 * t:4 * t + 4] = E
            r0 += len(E)
        G = np.vstack(Gs)
        Pi = G @ np.linalg.pinv(G)
        sel = (8 * np.arange(n)[:, None] + 4 * coord + np.arange(4)[None, :]).ravel()
        Q[np.ix_(sel, sel)] = w * D.T @ (np.eye(len(D)) - Pi) @ D
    scale = np.abs(Q).max()
    assert np.abs(tie.dense_q() - Q).max() < 1e-9 * scale
    assert np.array_equal(tie.idx, np.arange(16, 16 + 8 * n))
    flat = rng.normal(size=8 * (n + 2))
    p = flat[tie.idx]
    assert np.allclose(tie.grad(flat), Q @ p, rtol=0, atol=1e-9 * scale * np.abs(p).sum())
    assert np.allclose(tie.diag(), np.diag(Q), rtol=0, atol=1e-9 * scale)
    assert abs(tie.cost(flat) - 0.5 * p @ Q @ p) < 1e-9 * scale * (p ** 2).sum()


def test_correction_at_reproduces_the_tile_field():
    """SparseModel.correction_at: the within-tile correction at any pixel of a tile, from the
    correction its tie points carry (a quadratic field is reproduced exactly; a tile without a
    correction gives zero)."""
    from recon_core.model.sparse_model import Observations, SparseModel
    from recon_core.model.tiling import tile_image

    tiles = tile_image("a.tif", 1500, 1000, 1000)
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 999, (400, 2))
    inside = np.stack([t.contains(xy) for t in tiles])          # (T, n)
    tile = np.concatenate([np.full(int(m.sum()), t) for t, m in enumerate(inside)])
    pix = np.concatenate([xy[m] for m in inside])

    def field(p):
        u, v = (p[:, 0] - 700.0) / 500.0, (p[:, 1] - 500.0) / 500.0
        return np.stack([0.05 * u * u - 0.02 * u * v, 0.03 * v * v + 0.01 * u], 1)

    corr = np.where((tile == 0)[:, None], field(pix), 0.0)
    # a third of the observations have no point (never triangulated): they carry no correction
    has = rng.uniform(size=len(tile)) > 0.33
    corr[~has] = 0.0
    obs = Observations(tile, np.arange(len(tile)), pix, np.zeros(len(tile), int), np.ones(len(tile), bool), corr)
    m = SparseModel(0, ["a.tif"], tiles, np.zeros((len(tiles), 2, 4)), np.ones(len(tiles), bool),
                    np.zeros((len(tiles), 2, 4), bool), obs, np.zeros((len(tile), 3)), has,
                    np.zeros(len(tile), np.uint8))
    q = np.array([[10.0, 20.0], [512.5, 900.0], [980.0, 3.0]])
    np.testing.assert_allclose(m.correction_at(0, q), field(q), atol=1e-12)
    np.testing.assert_allclose(m.correction_fields([0, 1])[0](q), field(q), atol=1e-12)
    assert not m.correction_at(1, q).any() and m.correction_fields([0, 1])[1] is None
