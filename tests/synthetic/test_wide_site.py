"""The bend of tile-camera bundle adjustment on a wide site, measured against the truth
(render-free: true pushbroom projections of points on the true scene, seeded noise)."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.bend.pushbroom import tile_corrections
from recon_core.synthetic.wide_site import make_wide_site, observability, structure_vs_truth


@pytest.fixture(scope="module")
def flat_site():
    # the `flat` preset's three ~5000 px views over ~2.5 km, d = 1000
    return make_wide_site("flat", 0, n_points=12000, noise_px=0.1, d=1000)


@pytest.fixture(scope="module")
def untied(flat_site):
    return flat_site.adjust(flat_site.best_tile_cameras(flat_site.X_true), flat_site.X_true)


def test_true_structure_fits_the_tiles_to_the_noise_level(flat_site):
    """The harness itself: the truth with its best tile cameras reprojects at the noise level
    (0.1 px per coordinate) plus the small within-tile departure from affine."""
    P = flat_site.best_tile_cameras(flat_site.X_true)
    r = np.einsum("kij,kj->ki", P[flat_site.obs_cam, :, :3], flat_site.X_true[flat_site.obs_pt]) \
        + P[flat_site.obs_cam, :, 3] - flat_site.obs_xy
    rms = float(np.sqrt((r ** 2).sum(1).mean()))
    assert 0.13 < rms < 0.16


def test_independent_tile_cameras_bend_a_wide_site(untied, flat_site):
    """Started from the truth, the adjustment of independent tile cameras walks into a bend of
    more than half a metre over 2.5 km that a best-fit affine map cannot remove (README,
    "Scale"): the open problem the per-image model is for."""
    s = structure_vs_truth(untied.X, flat_site.X_true)
    assert s["quadratic_range_m"] > 0.8
    assert s["quadratic_rms_m"] > 0.6 * s["rms_u_m"]          # the residual is a smooth bend


def test_within_tile_correction_removes_what_drives_the_bend(untied, flat_site):
    """The bend is driven: the truth is not where independent affine tile cameras fit best
    (the pushbroom departs from affine inside each tile, and a bend makes every image a little
    more affine). With each observation moved by its image model's departure from affine inside
    its tile (fitted to the observations at the start), the same adjustment from the same start
    stays within a few decimetres of the truth: the model is what holds the structure."""
    o = flat_site
    corr, info = tile_corrections(o.X_true[o.obs_pt], o.obs_xy, o.obs_cam, o.tile_image[o.obs_cam])
    assert info["images"] == [0, 1, 2] and 0.01 < info["rms_px"] < 0.1 and info["max_px"] < 0.3
    raw = o.obs_xy
    try:
        o.obs_xy = raw - corr
        res = o.adjust(o.best_tile_cameras(o.X_true), o.X_true)
    finally:
        o.obs_xy = raw
    s = structure_vs_truth(res.X, o.X_true)
    bent = structure_vs_truth(untied.X, o.X_true)
    assert s["quadratic_range_m"] < 0.3 < 0.8 < bent["quadratic_range_m"]
    assert s["rms_m"] < 0.6 * bent["rms_m"]
    # what is left is the points' noise, not a bend
    assert s["quadratic_rms_m"] < 0.5 * s["local_rms_m"]


def test_within_tile_correction_is_zero_for_affine_data():
    """An image whose tiles see exactly affine data gets no correction (an affine projection
    is its own best affine approximation on every tile), and an image with too few tiles none."""
    rng = np.random.default_rng(3)
    X = rng.uniform(-500, 500, (4000, 3)) * [1, 1, 0.05]
    P = np.array([[2.0, 0.1, 0.4, 3000.0], [-0.05, 2.0, -0.8, 2500.0]])
    xy = X @ P[:, :3].T + P[:, 3]
    tile = (X[:, 0] > 0).astype(int) * 2 + (X[:, 1] > 0).astype(int)
    corr, info = tile_corrections(X, xy, tile, np.zeros(len(X), int))
    assert info["images"] == [0] and np.abs(corr).max() < 1e-6
    corr, info = tile_corrections(X, xy + 1e-6 * X[:, :2] ** 2, tile, np.zeros(len(X), int), min_tiles=5)
    assert info["images"] == [] and not corr.any()


def test_what_the_views_can_see_of_a_bend():
    """The image model's ambiguity, worked out (docs: "The image model and the bend"): a
    quadratic warp of the structure moves each image's pixels; what its model re-fits is
    invisible. With models that cover a real focal plane (a bowed line's c^2 in the row), no
    warp moves the pixels of `flat`'s 3 views or of `large`'s 9 views of three dates by more
    than 3 thousandths of a pixel per metre: a dome or a saddle cannot be read from the images
    through their models, only held by what is known outside them (GCPs, a reference DEM).
    Once H_A gives metres and each image's 1D perspective is known by physics (its depth term
    fixed), 3 of `flat`'s warps are seen, none of them vertical."""
    site = make_wide_site("flat", 0, n_points=6000, noise_px=0.0, d=1000)
    s = np.array(observability(site)["singular_px_per_m"])
    assert s.max() < 2e-3
    phys = observability(site, altitude_m=660e3)
    sp = np.array(phys["singular_px_per_m"])
    assert np.sum(sp > 0.05) == 3 and sp[3] < 2e-3
    assert np.all(np.linalg.norm(phys["warps"][:3, 6:], axis=1) < 0.4)        # seen: horizontal
    assert np.all(np.linalg.norm(phys["warps"][-3:, 6:], axis=1) > 0.9)       # unseen: vertical
    large = observability(make_wide_site("large", 0, n_points=6000, noise_px=0.0, d=2000))
    assert np.max(large["singular_px_per_m"]) < 3e-3


@pytest.fixture(scope="module")
def large_views():
    return make_wide_site("large", 0, n_points=6000, noise_px=0.1, d=2000)


def _domed(X, e_m: float = 0.5, n_m: float = 0.25, en_m: float = -0.3):
    """X (metric) with a dome and a saddle added to its height (metres at the site's edge)."""
    e, n = X[:, 0] - X[:, 0].mean(), X[:, 1] - X[:, 1].mean()
    h = max(np.ptp(e), np.ptp(n)) / 2.0
    out = X.copy()
    out[:, 2] += e_m * (e / h) ** 2 + n_m * (n / h) ** 2 + en_m * e * n / h ** 2
    return out


def test_a_bend_is_what_a_bowed_focal_plane_looks_like(large_views):
    """Why the bend step needs straight line arrays (docs: "The image model and the bend"): `large`'s 9 views,
    the true structure domed by 0.9 m peak to peak and put in an arbitrary affine frame. Through
    image models that cover a real focal plane (a bowed line: the row's c^2), no warp of the
    structure moves the pixels beyond what each image's model re-fits: every share is below
    0.01 (before the focal-plane terms the weakest of 7 seen was 0.027), so nothing can tell a
    dome from the sensors' own bows, and estimate_bend leaves the structure as it is. The
    shares are the same in a metric and in an affine frame."""
    from recon_core.bend.pushbroom import estimate_bend

    site = large_views
    Xt = site.X_true
    bent = _domed(Xt)
    assert structure_vs_truth(bent, Xt)["quadratic_range_m"] > 0.8
    rng = np.random.default_rng(5)
    A = np.eye(3) + 0.4 * rng.normal(size=(3, 3))
    A[:, 2] *= 6.0                                       # a stretched vertical, as an affine SfM's
    shares = []
    for F, shift in ((np.eye(3), 0.0), (A, np.array([40.0, -300.0, 7.0]))):
        Xf = bent @ F.T + shift
        warp, info = estimate_bend(Xf, site.views_per_image())
        assert info["warps_seen"] == 0 and max(info["warp_shares"]) < 0.01
        assert np.abs(warp(Xf)).max() == 0.0
        shares.append(info["warp_shares"])
    np.testing.assert_allclose(shares[0], shares[1], rtol=1e-6, atol=1e-9)


def test_bend_step_read_by_chunks_is_the_same_estimate(large_views):
    """estimate_bend reads each image's equations by chunks (a tall-skinny QR): with chunks of
    997 observations, on a bent and on a flat (rank-deficient model basis) structure, the warp,
    the shares, the residual and the observations kept are those of one chunk."""
    from recon_core.bend.pushbroom import estimate_bend

    site = large_views
    views = site.views_per_image()
    assert max(len(p) for p, _ in views) > 5 * 997
    flat = site.X_true.copy()
    flat[:, 2] = 0.0
    for X, seen in ((_domed(site.X_true), 9), (flat, 0)):
        # (a low min_share: every warp the views see at all is estimated, however weakly)
        one, i1 = estimate_bend(X, views, chunk=10 ** 7, min_share=1e-4)
        many, i2 = estimate_bend(X, views, chunk=997, min_share=1e-4)
        assert i1["warps_seen"] == i2["warps_seen"] and (i1["warps_seen"] > 0) == (seen > 0)
        np.testing.assert_allclose(many(X), one(X), atol=1e-9 * np.abs(one(X)).max())
        np.testing.assert_allclose(i2["warp_shares"], i1["warp_shares"], rtol=1e-6, atol=1e-7)
        assert abs(i2["residual_rms_px"] - i1["residual_rms_px"]) < 1e-9


def test_bend_warp_cameras_follow():
    """BendWarp: its Jacobian is the derivative of its displacement, and an affine camera moved
    with it (`follow`) sees the warped points where it saw the points, up to the warp's
    curvature over the camera's patch."""
    from recon_core.geometry.enu_map import BendWarp

    rng = np.random.default_rng(0)
    T = np.eye(3) + 0.2 * rng.normal(size=(3, 3))
    warp = BendWarp(np.zeros(3), T, np.array([[1e-3, 0, 0], [0, 1e-3, 0]]), np.zeros(3),
                    0.5 * rng.normal(size=9))
    X = np.column_stack([rng.uniform(1000, 1030, 200), rng.uniform(-500, -470, 200), rng.uniform(0, 5, 200)])
    eps = 1e-4
    num = np.stack([(warp(X[:3] + eps * np.eye(3)[j]) - warp(X[:3] - eps * np.eye(3)[j])) / (2 * eps)
                    for j in range(3)], 2)
    np.testing.assert_allclose(warp.jacobian(X[:3]), num, atol=1e-8)
    P = rng.normal(size=(1, 2, 4))
    seen = np.hstack([X, np.ones((200, 1))]) @ P[0].T
    moved = np.hstack([X + warp(X), np.ones((200, 1))])
    assert np.abs(moved @ P[0].T - seen).max() > 0.1           # the warp moves the pixels
    assert np.abs(moved @ warp.follow(P, X.mean(0)[None])[0].T - seen).max() < 1e-3


def test_the_expected_bend_is_the_size_of_the_bend(untied, flat_site):
    """bend.drive: where the views cannot see a bend, the size the images' own departures from
    affine drive it to. On `flat` (3 views over 2.5 km), the structure the adjustment of
    independent tile cameras settles on is bent by about 0.35 m RMS (quadratic, beyond an
    affine map); the estimate, made from the images and the structure alone in the frame of the
    best affine map (as the upgrade's H_A gives it), is within a factor of 2.5 of it."""
    from recon_core.bend.drive import expected_bend

    X, Xt = untied.X, flat_site.X_true
    A = np.hstack([X, np.ones((len(X), 1))])
    Y = A @ np.linalg.lstsq(A, Xt, rcond=None)[0]
    d = expected_bend(Y, flat_site.views_per_image(20000, 0))
    # the actual bend: the quadratic part of the vertical residual, beyond an affine map
    e, n = ((Y[:, :2] - Y[:, :2].mean(0)) / (np.ptp(Y[:, :2], axis=0).max() / 2)).T
    lin = np.column_stack([np.ones_like(e), e, n])
    quad = np.column_stack([e * e, e * n, n * n])
    q = np.hstack([lin, quad]) @ np.linalg.lstsq(np.hstack([lin, quad]), Y[:, 2] - Xt[:, 2], rcond=None)[0]
    actual = float((q - lin @ np.linalg.lstsq(lin, q, rcond=None)[0]).std())
    assert actual > 0.2
    assert d is not None and d.views == 3 and d.dof == 9
    assert actual / 2.5 < d.expected_rms_m < actual * 2.5
    assert d.expected_edge_m > d.expected_rms_m


def test_no_departure_from_affine_no_expected_bend():
    """Images that are exactly affine drive no bend: the expected bend is nil, and with one
    image there is nothing to estimate."""
    from recon_core.bend.drive import expected_bend

    rng = np.random.default_rng(5)
    Y = rng.uniform(-1200, 1200, (3000, 3)) * [1, 1, 0.01]
    images = []
    for P in (np.array([[2.0, 0.1, 0.6, 2500.0], [-0.1, 2.0, -0.9, 2400.0]]),
              np.array([[2.0, -0.2, -0.3, 2600.0], [0.2, 2.0, 0.8, 2500.0]]),
              np.array([[1.9, 0.0, 0.1, 2450.0], [0.0, 2.1, 0.3, 2550.0]])):
        k = np.sort(rng.choice(len(Y), 2000, replace=False))
        images.append((k, Y[k] @ P[:, :3].T + P[:, 3]))
    d = expected_bend(Y, images)
    assert d is not None and d.expected_rms_m < 1e-6 and d.departure_px < 1e-6
    assert expected_bend(Y, images[:1]) is None
