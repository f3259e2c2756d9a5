"""Tests of recon_core.geometry.affine against independent checks (ground truth, never its own output)."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.errors import ReconstructionError
from recon_core.geometry import affine as af

SCENE_CENTRE = np.array([500.0, 500.0, 25.0])


# ------------------------------------------------------------------------------------------------
# synthetic satellite-like data
# ------------------------------------------------------------------------------------------------
def sat_camera(zenith_deg, azimuth_deg, kappa_deg=0.0, scale=1.0, aniso=0.0, skew=0.0,
               offset=(600.0, 550.0)):
    """Affine camera looking at the scene from direction (zenith, azimuth), ~`scale` px/m.

    Image axes (u1, u2) are orthonormal, perpendicular to the view direction d and rotated by
    kappa in the image plane; u1 x u2 = -d (col = east, row = south at nadir), like every
    satellite image, so all cameras have the same handedness.
    """
    zt, az, kp = np.radians([zenith_deg, azimuth_deg, kappa_deg])
    d = np.array([np.sin(zt) * np.cos(az), np.sin(zt) * np.sin(az), np.cos(zt)])
    ez = np.array([0.0, 0.0, 1.0])
    axis = np.cross(ez, d)
    sa = np.linalg.norm(axis)
    if sa < 1e-12:
        Rv = np.eye(3)
    else:
        k = axis / sa
        K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        Rv = np.eye(3) + sa * K + (1 - d @ ez) * K @ K
    c, s = np.cos(kp), np.sin(kp)
    u1 = Rv @ np.array([c, s, 0.0])
    u2 = Rv @ np.array([s, -c, 0.0])
    assert np.allclose(np.cross(u1, u2), -d)
    Kc = scale * np.array([[1.0 + aniso, skew], [0.0, 1.0 - aniso]])
    M = Kc @ np.vstack([u1, u2])
    t = np.asarray(offset) - M @ SCENE_CENTRE
    return np.hstack([M, t[:, None]])


def scene_points(rng, n, relief=50.0):
    X = rng.uniform(0.0, 1000.0, size=(n, 3))
    X[:, 2] = rng.uniform(0.0, relief, size=n)
    return X


def five_cameras():
    return np.stack(
        [
            sat_camera(0.0, 0.0, 0.0),
            sat_camera(20.0, 100.0, 8.0, scale=1.05, aniso=0.01, skew=0.01),
            sat_camera(25.0, 280.0, -12.0, scale=0.95, aniso=-0.02, skew=0.005),
            sat_camera(15.0, 190.0, 3.0, scale=1.1),
            sat_camera(30.0, 10.0, 170.0, scale=0.9, skew=-0.01),
        ]
    )


def homog_F_value(F, x1, x2):
    """x2^T F x1 computed with homogeneous matrices (independent of fa_residuals)."""
    h1 = np.column_stack([x1, np.ones(len(x1))])
    h2 = np.column_stack([x2, np.ones(len(x2))])
    return np.einsum("ni,ij,nj->n", h2, F, h1)


def unit_F(F):
    """Scale F so (a, b, c, d) has unit norm and its largest-magnitude entry is positive."""
    N = np.array([F[0, 2], F[1, 2], F[2, 0], F[2, 1]])
    F = F / np.linalg.norm(N)
    N = N / np.linalg.norm(N)
    return F * np.sign(N[np.argmax(np.abs(N))])


def corrupt(rng, x, frac, lo=0.0, hi=1200.0):
    """Replace a fraction of the points by uniform random pixels; returns (x', outlier_mask)."""
    n = len(x)
    out = np.zeros(n, bool)
    out[rng.choice(n, int(round(frac * n)), replace=False)] = True
    x = x.copy()
    x[out] = rng.uniform(lo, hi, size=(out.sum(), 2))
    return x, out


# ------------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------------
def test_project_single_and_stack():
    rng = np.random.default_rng(0)
    cams = five_cameras()
    X = scene_points(rng, 50)
    stacked = af.project(cams, X)
    assert stacked.shape == (5, 50, 2)
    for i, P in enumerate(cams):
        Xh = np.column_stack([X, np.ones(len(X))])
        np.testing.assert_allclose(af.project(P, X), (P @ Xh.T).T, atol=1e-12)
        np.testing.assert_allclose(stacked[i], (P @ Xh.T).T, atol=1e-12)


@pytest.mark.parametrize("dim", [2, 3])
def test_normalize_points(dim):
    rng = np.random.default_rng(1)
    x = rng.normal(size=(100, dim)) * 300 + 1e5
    xn, T = af.normalize_points(x)
    np.testing.assert_allclose(xn.mean(axis=0), 0, atol=1e-9)
    assert np.sqrt(np.mean(np.sum(xn**2, axis=1))) == pytest.approx(np.sqrt(dim), rel=1e-9)
    xh = np.column_stack([x, np.ones(len(x))])
    np.testing.assert_allclose((T @ xh.T).T[:, :dim], xn, atol=1e-9)
    assert np.allclose(T[dim], np.eye(dim + 1)[dim])


def test_fit_affine_3d_recovers_known_map():
    rng = np.random.default_rng(2)
    X = scene_points(rng, 200)
    A = np.hstack([rng.normal(size=(3, 3)) + 2 * np.eye(3), rng.normal(size=(3, 1)) * 1e3])
    Y = X @ A[:, :3].T + A[:, 3]
    A_est = af.fit_affine_3d(X, Y)
    np.testing.assert_allclose(A_est, A, rtol=0, atol=1e-8 * np.abs(A).max())
    np.testing.assert_allclose(af.apply_affine_3d(A_est, X), Y, atol=1e-7)
    # weights: a corrupted point with zero weight does not matter
    Y2 = Y.copy()
    Y2[0] += 100.0
    w = np.ones(len(X))
    w[0] = 0.0
    np.testing.assert_allclose(af.fit_affine_3d(X, Y2, weights=w), A, atol=1e-8 * np.abs(A).max())


# ------------------------------------------------------------------------------------------------
# exact data
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("m", [2, 4])
def test_tomasi_kanade_exact(m):
    rng = np.random.default_rng(3)
    cams_true = five_cameras()[:m]
    X_true = scene_points(rng, 300)
    W = af.project(cams_true, X_true)
    cams, X, s = af.tomasi_kanade(W)
    assert cams.shape == (m, 2, 4) and X.shape == (300, 3)
    assert np.abs(af.project(cams, X) - W).max() < 1e-9
    assert s[3] < 1e-12 * s[0] and s[2] > 1e-3 * s[0]
    A = af.fit_affine_3d(X, X_true)
    assert np.abs(af.apply_affine_3d(A, X) - X_true).max() < 1e-6


def test_canonical_gauge_form_projections_and_uniqueness():
    rng = np.random.default_rng(4)
    cams = five_cameras()[[1, 2, 0]]
    X = scene_points(rng, 100)
    cams_c, Xc, A = af.canonical_gauge(cams, X)
    assert A.shape == (4, 4) and np.allclose(A[3], [0, 0, 0, 1])
    np.testing.assert_allclose(cams_c[0], [[1, 0, 0, 0], [0, 1, 0, 0]], atol=1e-12)
    r = int(np.argmax(np.abs(cams_c[1, :, 2])))
    np.testing.assert_allclose(cams_c[1, r], [0, 0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(Xc, X @ A[:3, :3].T + A[:3, 3], atol=1e-9)
    np.testing.assert_allclose(af.project(cams_c, Xc), af.project(cams, X), atol=1e-9)
    # exactly 12 dof fixed: any affinely transformed copy lands on the same canonical result
    B = np.eye(4)
    B[:3] = np.hstack([rng.normal(size=(3, 3)) + 3 * np.eye(3), rng.normal(size=(3, 1)) * 100])
    cams_b = cams @ np.linalg.inv(B)
    X_b = X @ B[:3, :3].T + B[:3, 3]
    cams_c2, Xc2, _ = af.canonical_gauge(cams_b, X_b)
    np.testing.assert_allclose(cams_c2, cams_c, atol=1e-9)
    np.testing.assert_allclose(Xc2, Xc, atol=1e-6 * np.abs(Xc).max())


def test_canonical_gauge_same_direction_raises():
    P1 = sat_camera(10.0, 40.0, 0.0)
    P2 = sat_camera(10.0, 40.0, 30.0, scale=1.2)
    with pytest.raises(ReconstructionError):
        af.canonical_gauge(np.stack([P1, P2]), np.zeros((5, 3)))


def test_resect_exact():
    rng = np.random.default_rng(5)
    X = scene_points(rng, 200)
    for P_true in five_cameras():
        P = af.resect(X, af.project(P_true, X))
        assert np.abs(P - P_true).max() < 1e-9
    # minimal set of 4 and weights
    P_true = five_cameras()[2]
    assert np.abs(af.resect(X[:4], af.project(P_true, X[:4])) - P_true).max() < 1e-9
    x = af.project(P_true, X)
    x[:10] += 50.0
    w = np.ones(len(X))
    w[:10] = 0.0
    assert np.abs(af.resect(X, x, weights=w) - P_true).max() < 1e-9


@pytest.mark.parametrize("seed", [6, 7])
def test_triangulate_tracks_exact_2_to_5_views(seed):
    rng = np.random.default_rng(seed)
    cams = five_cameras()
    n = 400
    X_true = scene_points(rng, n)
    nviews = rng.integers(2, 6, size=n)
    cam_idx, pt_idx = [], []
    for p in range(n):  # building the test data only
        cs = rng.choice(5, nviews[p], replace=False)
        cam_idx += list(cs)
        pt_idx += [p] * len(cs)
    cam_idx = np.array(cam_idx)
    pt_idx = np.array(pt_idx)
    perm = rng.permutation(len(cam_idx))  # observations in arbitrary order
    cam_idx, pt_idx = cam_idx[perm], pt_idx[perm]
    xy = np.einsum("kij,kj->ki", cams[cam_idx, :, :3], X_true[pt_idx]) + cams[cam_idx, :, 3]
    X, ok = af.triangulate_tracks(cams, cam_idx, pt_idx, xy, n)
    assert ok.all()
    assert np.abs(X - X_true).max() < 1e-9
    for v in range(2, 6):
        assert np.any(nviews == v)


def test_triangulate_tracks_degenerate_and_weights():
    rng = np.random.default_rng(8)
    cams = five_cameras()
    X_true = scene_points(rng, 5)
    # point 0: one view; point 1: twice the same camera; point 2: no observation;
    # point 3: three views, one corrupted but weight 0; point 4: two views
    cam_idx = np.array([1, 2, 2, 0, 1, 3, 0, 4])
    pt_idx = np.array([0, 1, 1, 3, 3, 3, 4, 4])
    xy = np.einsum("kij,kj->ki", cams[cam_idx, :, :3], X_true[pt_idx]) + cams[cam_idx, :, 3]
    xy[1] += 0.5  # same camera twice: inconsistent but still rank 2
    xy[5] += 40.0
    w = np.ones(len(cam_idx))
    w[5] = 0.0
    X, ok = af.triangulate_tracks(cams, cam_idx, pt_idx, xy, 5, weights=w)
    np.testing.assert_array_equal(ok, [False, False, False, True, True])
    assert np.all(np.isnan(X[~ok]))
    assert np.abs(X[ok] - X_true[ok]).max() < 1e-9


def test_reprojection_errors_known_offsets():
    rng = np.random.default_rng(9)
    cams = five_cameras()
    X = scene_points(rng, 30)
    cam_idx = rng.integers(0, 5, 100)
    pt_idx = rng.integers(0, 30, 100)
    proj = af.project(cams, X)  # (5, 30, 2)
    lengths = rng.uniform(0, 3, 100)
    ang = rng.uniform(0, 2 * np.pi, 100)
    xy = proj[cam_idx, pt_idx] + lengths[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    np.testing.assert_allclose(af.reprojection_errors(cams, cam_idx, pt_idx, xy, X), lengths,
                               atol=1e-9)


def test_fundamental_gold_standard_and_from_cameras_agree_exact():
    rng = np.random.default_rng(10)
    cams = five_cameras()
    X = scene_points(rng, 200)
    for i, j in [(0, 1), (1, 2), (3, 4), (2, 0)]:
        x1, x2 = af.project(cams[i], X), af.project(cams[j], X)
        Fg = af.affine_fundamental_gold_standard(x1, x2)
        Fc = af.affine_fundamental_from_cameras(cams[i], cams[j])
        for F in (Fg, Fc):
            assert np.all(F[:2, :2] == 0)
            # x2^T F x1 = 0 (scale: ||(a,b,c,d)|| = 1, coordinates ~ 1e3 px)
            assert np.abs(homog_F_value(F, x1, x2)).max() < 1e-9
            assert np.linalg.norm([F[0, 2], F[1, 2], F[2, 0], F[2, 1]]) == pytest.approx(1.0)
        np.testing.assert_allclose(unit_F(Fg), unit_F(Fc), atol=1e-9)
        # swapping the images transposes F (convention check)
        Fc_swap = af.affine_fundamental_from_cameras(cams[j], cams[i])
        np.testing.assert_allclose(unit_F(Fc_swap), unit_F(Fc.T), atol=1e-12)


def test_fa_residuals_and_epipolar_distances_are_geometric():
    rng = np.random.default_rng(11)
    cams = five_cameras()
    X = scene_points(rng, 50)
    x1, x2 = af.project(cams[0], X), af.project(cams[2], X)
    F = af.affine_fundamental_from_cameras(cams[0], cams[2])
    a, b, c, d = F[0, 2], F[1, 2], F[2, 0], F[2, 1]
    N = np.array([a, b, c, d])
    N /= np.linalg.norm(N)
    delta = rng.uniform(-3, 3, 50)
    # move the joint point (x2, x1) along the unit normal: orthogonal distance = |delta|
    y2 = x2 + delta[:, None] * N[:2]
    y1 = x1 + delta[:, None] * N[2:]
    np.testing.assert_allclose(af.fa_residuals(F, y1, y2), np.abs(delta), atol=1e-9)
    # move only x2 perpendicular to its epipolar line (normal (a, b)): d2 = |delta|, d1 scaled
    nab = np.array([a, b]) / np.hypot(a, b)
    z2 = x2 + delta[:, None] * nab
    d1, d2 = af.epipolar_distances(F, x1, z2)
    np.testing.assert_allclose(d2, np.abs(delta), atol=1e-9)
    np.testing.assert_allclose(d1, np.abs(delta) * np.hypot(a, b) / np.hypot(c, d), atol=1e-9)
    # moving x2 along its epipolar line changes nothing
    along = np.array([-nab[1], nab[0]])
    np.testing.assert_allclose(af.fa_residuals(F, x1, x2 + 7.0 * along), 0, atol=1e-9)


def _rectify_checks(H1, H2):
    for H in (H1, H2):
        assert np.allclose(H[2], [0, 0, 1])
        assert np.linalg.det(H[:2, :2]) > 0  # no mirror
        sv = np.linalg.svd(H[:2, :2], compute_uv=False)
        assert 0.6 < sv[1] <= sv[0] < 1.6  # modest scale distortion for ~1 px/m images


@pytest.mark.parametrize("pair", [(0, 1), (1, 2), (4, 3), (2, 4)])
def test_rectification_exact(pair):
    rng = np.random.default_rng(12)
    cams = five_cameras()
    P1, P2 = cams[pair[0]], cams[pair[1]]
    X = scene_points(rng, 300)
    x1, x2 = af.project(P1, X), af.project(P2, X)
    F = af.affine_fundamental_from_cameras(P1, P2)
    H1, H2 = af.rectifying_maps(F, x1, x2)
    p1 = x1 @ H1[:2, :2].T + H1[:2, 2]
    p2 = x2 @ H2[:2, :2].T + H2[:2, 2]
    assert np.abs(p1[:, 1] - p2[:, 1]).max() < 1e-9
    np.testing.assert_allclose(af.rectified_row_error(H1, H2, x1, x2), p1[:, 1] - p2[:, 1],
                               atol=1e-12)
    _rectify_checks(H1, H2)
    # horizontal registration: disparities are centred and much smaller than the raw offsets
    disp = p2[:, 0] - p1[:, 0]
    assert abs(disp.mean()) < 1e-6
    assert np.abs(disp).max() < 40.0  # only the 50 m of relief remains
    # shape1 translation: image-1 corners start at (0, 0), rows and disparities unchanged
    G1, G2 = af.rectifying_maps(F, x1, x2, shape1=(1100, 1200))
    corners = np.array([[0, 0], [1200, 0], [1200, 1100], [0, 1100]], float)
    np.testing.assert_allclose(af.apply_affine_2d(G1, corners).min(axis=0), 0, atol=1e-9)
    q1, q2 = af.apply_affine_2d(G1, x1), af.apply_affine_2d(G2, x2)
    assert np.abs(q1[:, 1] - q2[:, 1]).max() < 1e-9
    np.testing.assert_allclose(q2[:, 0] - q1[:, 0], disp, atol=1e-9)


def test_rectification_mirrored_input():
    rng = np.random.default_rng(13)
    cams = five_cameras()
    X = scene_points(rng, 200)
    P1 = cams[0]
    P2 = cams[1].copy()
    P2[0] *= -1.0  # image 2 mirrored (x -> -x)
    x1, x2 = af.project(P1, X), af.project(P2, X)
    F = af.affine_fundamental_from_cameras(P1, P2)
    with pytest.raises(ReconstructionError):
        af.rectifying_maps(F, x1, x2)
    H1, H2 = af.rectifying_maps(F, x1, x2, allow_mirror=True)
    assert np.linalg.det(H2[:2, :2]) < 0 < np.linalg.det(H1[:2, :2])
    assert np.abs(af.rectified_row_error(H1, H2, x1, x2)).max() < 1e-9


@pytest.mark.parametrize("pair", [(0, 1), (2, 4)])
def test_disparity_to_3d_map_exact(pair):
    rng = np.random.default_rng(14)
    cams = five_cameras()
    P1, P2 = cams[pair[0]], cams[pair[1]]
    X = scene_points(rng, 300)
    x1, x2 = af.project(P1, X), af.project(P2, X)
    F = af.affine_fundamental_from_cameras(P1, P2)
    H1, H2 = af.rectifying_maps(F, x1, x2, shape1=(1000, 1000))
    p1 = x1 @ H1[:2, :2].T + H1[:2, 2]
    p2 = x2 @ H2[:2, :2].T + H2[:2, 2]
    u, v, d = p1[:, 0], p1[:, 1], p2[:, 0] - p1[:, 0]  # x2' = u + d, y2' = v
    L = af.disparity_to_3d_map(P1, P2, H1, H2)
    assert L.shape == (3, 4)
    Xr = (L @ np.column_stack([u, v, d, np.ones_like(u)]).T).T
    assert np.abs(Xr - X).max() < 1e-6
    np.testing.assert_allclose(af.apply_disparity_map(L, u, v, d), Xr, atol=1e-9)
    # disparity of a point changes linearly with its height along a vertical line
    Xa = X.copy()
    Xa[:, 2] += 10.0
    pa1 = af.apply_affine_2d(H1, af.project(P1, Xa))
    pa2 = af.apply_affine_2d(H2, af.project(P2, Xa))
    dd = (pa2[:, 0] - pa1[:, 0]) - d
    assert np.ptp(dd) < 1e-6 and abs(dd[0]) > 1.0


# ------------------------------------------------------------------------------------------------
# noise and outliers
# ------------------------------------------------------------------------------------------------
def test_resect_ransac_noise_outliers():
    rng = np.random.default_rng(20)
    P_true = five_cameras()[1]
    X = scene_points(rng, 400)
    x = af.project(P_true, X) + rng.normal(scale=0.3, size=(400, 2))
    x, out = corrupt(rng, x, 0.3)
    P, inl = af.resect_ransac(X, x, thresh_px=2.0, iters=500, rng=1)
    # error versus the true camera over a grid spanning the scene volume
    g = np.stack(np.meshgrid(np.linspace(0, 1000, 6), np.linspace(0, 1000, 6),
                             np.linspace(0, 50, 3)), -1).reshape(-1, 3)
    err = np.linalg.norm(af.project(P, g) - af.project(P_true, g), axis=1)
    assert err.max() < 0.3
    assert (inl & ~out).sum() / (~out).sum() > 0.95
    assert (~inl & out).sum() / out.sum() > 0.95


def test_resect_ransac_too_few_inliers_raises():
    rng = np.random.default_rng(21)
    X = scene_points(rng, 40)
    x = rng.uniform(0, 1000, size=(40, 2))
    with pytest.raises(ReconstructionError):
        af.resect_ransac(X, x, thresh_px=0.5, iters=200, rng=0, min_inliers=10)


def test_fa_ransac_noise_outliers_and_rectification():
    rng = np.random.default_rng(22)
    cams = five_cameras()
    P1, P2 = cams[0], cams[2]
    X = scene_points(rng, 400)
    x1_true, x2_true = af.project(P1, X), af.project(P2, X)
    x1 = x1_true + rng.normal(scale=0.3, size=x1_true.shape)
    x2 = x2_true + rng.normal(scale=0.3, size=x2_true.shape)
    x2, out = corrupt(rng, x2, 0.3)
    F, inl = af.fa_ransac(x1, x2, thresh_px=1.0, iters=1000, rng=2)
    # versus the truth: the exact correspondences nearly satisfy the estimated F
    res_true = af.fa_residuals(F, x1_true, x2_true)
    assert np.sqrt(np.mean(res_true**2)) < 0.1
    F_true = af.affine_fundamental_from_cameras(P1, P2)
    # normal (a, b, c, d) within ~ sigma / sigma3 (0.3 px / 88 px of parallax spread) of the truth
    Nf = unit_F(F)[[0, 1, 2, 2], [2, 2, 0, 1]]
    Nt = unit_F(F_true)[[0, 1, 2, 2], [2, 2, 0, 1]]
    assert np.linalg.norm(Nf - Nt) < 0.01
    assert (inl & ~out).sum() / (~out).sum() > 0.95
    assert (~inl & out).sum() / out.sum() > 0.95
    # rectification from the noisy estimate
    H1, H2 = af.rectifying_maps(F, x1[inl], x2[inl])
    _rectify_checks(H1, H2)
    rms_true = np.sqrt(np.mean(af.rectified_row_error(H1, H2, x1_true, x2_true) ** 2))
    rms_noisy = np.sqrt(np.mean(af.rectified_row_error(H1, H2, x1[inl], x2[inl]) ** 2))
    assert rms_true < 0.1
    assert rms_noisy < 0.5


# ------------------------------------------------------------------------------------------------
# degenerate configurations
# ------------------------------------------------------------------------------------------------
def _noisy_pair(rng, P1, P2, X, sigma=0.3):
    x1 = af.project(P1, X) + rng.normal(scale=sigma, size=(len(X), 2))
    x2 = af.project(P2, X) + rng.normal(scale=sigma, size=(len(X), 2))
    return x1, x2


def test_parallax_detection():
    rng = np.random.default_rng(30)
    cams = five_cameras()
    X = scene_points(rng, 200)
    # flat (tilted plane) scene seen from two different directions
    Xf = X.copy()
    Xf[:, 2] = 10.0 + 0.02 * Xf[:, 0] - 0.01 * Xf[:, 1]
    flat = _noisy_pair(rng, cams[0], cams[1], Xf)
    # relief, but both views with the same direction (different roll and scale)
    same = _noisy_pair(rng, sat_camera(20, 100, 8), sat_camera(20, 100, 40, scale=1.2), X)
    # relief seen from two directions
    relief = _noisy_pair(rng, cams[0], cams[1], X)
    for x1, x2 in (flat, same):
        assert af.parallax_ratio(x1, x2) < 2.0
        assert af.parallax_stats(x1, x2)["ratio_32"] < 2e-3
        assert not af.affine_map_vs_fa_test(x1, x2, thresh=1.0, rng=0)
        assert not af.affine_map_vs_fa_test(x1, x2, thresh=1.0, sigma=0.3, rng=0)
    assert af.parallax_ratio(*relief) > 3 * af.PARALLAX_RATIO_MIN
    st = af.parallax_stats(*relief)
    assert st["ratio_32"] > 5e-3 and st["rms_noise_px"] == pytest.approx(0.3, rel=0.3)
    ok, det = af.affine_map_vs_fa_test(*relief, thresh=1.0, rng=0, return_details=True)
    assert ok and det["gric_fa"] < det["gric_affine"]
    assert af.affine_map_vs_fa_test(*relief, thresh=1.0, sigma=0.3, rng=0)
    # with 30 % outliers the robust test still sees the parallax, and still rejects flat
    x2o, _ = corrupt(rng, relief[1], 0.3)
    assert af.affine_map_vs_fa_test(relief[0], x2o, thresh=1.0, rng=0)
    x2f, _ = corrupt(rng, flat[1], 0.3)
    assert not af.affine_map_vs_fa_test(flat[0], x2f, thresh=1.0, rng=0)


def test_parallax_flat_ground_with_buildings_and_gric():
    rng = np.random.default_rng(32)
    cams = five_cameras()
    X = scene_points(rng, 300)
    X[:, 2] = 5.0
    bld = rng.random(300) < 0.2
    X[bld, 2] += rng.uniform(15.0, 40.0, bld.sum())  # 20 % of the points on buildings
    x1, x2 = _noisy_pair(rng, cams[0], cams[2], X)
    x2o, _ = corrupt(rng, x2, 0.3)
    ok, det = af.affine_map_vs_fa_test(x1, x2o, thresh=1.0, rng=1, return_details=True)
    assert ok and det["ratio_q90"] > 2.0 and det["parallax_fraction"] > 0.1
    # GRIC on clean inliers with the known noise: relief prefers F_A, a flat scene the affine map
    g = af.affine_map_vs_fa_gric(*_noisy_pair(rng, cams[0], cams[2], scene_points(rng, 200)),
                                 sigma=0.3, rng=0)
    assert g["prefers_fa"] and g["ratio_q90"] > 5
    Xf = scene_points(rng, 200)
    Xf[:, 2] = 0.0
    g = af.affine_map_vs_fa_gric(*_noisy_pair(rng, cams[0], cams[2], Xf), sigma=0.3, rng=0)
    assert not g["prefers_fa"] and g["ratio_q90"] < 1.6


def test_points_conditioning_flags_planar_resection():
    rng = np.random.default_rng(31)
    X = scene_points(rng, 200)
    Xp = X.copy()
    Xp[:, 2] = 5.0 + 0.01 * Xp[:, 0] + rng.normal(scale=0.01, size=200)  # ~1 cm off a plane
    assert af.points_conditioning(X) > 10 * af.PLANAR_CONDITIONING_MIN
    assert af.points_conditioning(Xp) < af.PLANAR_CONDITIONING_MIN
    # why it matters: with 0.3 px noise the out-of-plane column is not determined
    P_true = five_cameras()[2]
    errs = []
    for pts in (X, Xp):
        x = af.project(P_true, pts) + rng.normal(scale=0.3, size=(200, 2))
        P = af.resect(pts, x)
        errs.append(np.abs(P[:, 2] - P_true[:, 2]).max())
    assert errs[0] < 0.05 < errs[1]
