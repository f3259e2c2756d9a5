"""The per-image pushbroom tie (recon_core.sparse.image_model): its algebra against functions
known to be in or out of the model's family, its invariance to the affine gauge, and how it
enters the bundle adjustment."""

from __future__ import annotations

import numpy as np

from recon_core.sparse.bundle import bundle_adjust
from recon_core.sparse.image_model import col_basis, image_frame, image_tie, row_basis


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
                                uv[:, 1] + row_basis(Xn, r) @ theta_r])
    return fn


def _tie_rms(cams, samples):
    t = image_tie(cams, samples, np.arange(len(cams)), 1.0)
    return np.sqrt(2 * t.cost(cams.reshape(-1)) / (16 * len(cams)))


def test_tie_is_free_inside_the_pushbroom_family_and_costs_outside():
    rng = np.random.default_rng(0)
    samples = _tiles(rng)
    theta_r = np.r_[np.zeros(4), 0.8, -0.5, 0.3, 0.6]          # view plane turning, pitch drift
    theta_c = np.r_[np.zeros(4), 0.4, 0.7, -0.2, 0.9, -0.5]    # 1D perspective, roll drift
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
    assert _tie_rms(bent, samples) > 50 * free


def test_tie_follows_the_affine_gauge():
    """Moving the frame by a 3D affine map G (points G X, cameras P G^-1) leaves the tie's cost
    unchanged: the model's family is closed under affine maps."""
    rng = np.random.default_rng(1)
    samples = _tiles(rng, n_side=3)
    fn = _model_function(samples, np.r_[np.zeros(4), 0.5, 0.2, -0.4, 0.3],
                         np.r_[np.zeros(4), -0.3, 0.5, 0.1, 0.4, 0.2])
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
    fn = _model_function(samples, np.r_[np.zeros(4), 0.5, 0.2, -0.4, 0.3],
                         np.r_[np.zeros(4), -0.3, 0.5, 0.1, 0.4, 0.2])
    X = np.concatenate(samples)
    oc = np.repeat(np.arange(len(samples)), [len(s) for s in samples])
    op = np.arange(len(X))
    xy = fn(X) + rng.normal(0, 0.05, (len(X), 2))
    start = _affine_fits(fn, samples) + rng.normal(0, 0.02, (len(samples), 2, 4)) * [1, 1, 1, 10]
    tie = image_tie(start, samples, np.arange(len(samples)), 100.0)
    held = np.arange(0)                                        # points held: the frame is fixed
    runs = [bundle_adjust(start, X, oc, op, xy, np.arange(len(samples)), held, None, loss="linear",
                          ties=[tie], compiled=c) for c in (True, False)]
    for res in runs:
        assert res.cost_after < res.cost_before
        assert _tie_rms(res.cams, samples) < 0.5 * _tie_rms(start, samples)
    assert np.allclose(runs[0].cams, runs[1].cams, atol=1e-8)
    r = np.einsum("kij,kj->ki", runs[0].cams[oc, :, :3], X) + runs[0].cams[oc, :, 3] - xy
    assert runs[0].cost_after >= 0.5 * float((r ** 2).sum()) + tie.cost(runs[0].cams.reshape(-1)) - 1e-9
