"""H_A held by the images' lines of sight (recon_core.euclidean.held, sight): against a known
affine map, with render-free affine cameras whose lines of sight are the truth's."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.errors import ReconstructionError
from recon_core.euclidean.held import ControlPoints, fit_held, looseness
from recon_core.euclidean.sight import ViewRay, tile_sight, view_direction
from recon_core.euclidean.upgrade import GcpInput, ImageHold, upgrade
from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.geodesy import LocalFrame, enu_rotation
from recon_core.model.images import ViewAngles


def _truth(rng, n_images=6):
    """A random affine frame (H_true: affine -> ENU) and n_images views: (incidence, azimuth)
    and their affine cameras' linear parts, rows across each line of sight."""
    A = np.eye(3) + rng.normal(0, 0.3, (3, 3))
    A[:, 2] *= 0.05                                   # the affine frame squashes height, as SfM's does
    H = np.eye(4)
    H[:3, :3], H[:3, 3] = A, rng.normal(0, 50, 3)
    views, cams = [], []
    for _ in range(n_images):
        v = ViewAngles(float(rng.uniform(5, 30)), float(rng.uniform(0, 360)))
        s = view_direction(v)
        e1 = np.cross(s, [0.0, 0.0, 1.0])
        e1 /= np.linalg.norm(e1)
        M_enu = 2.0 * np.stack([e1, np.cross(s, e1)])    # 2 px per metre, rows across the sight
        views.append(v)
        cams.append(M_enu @ A)                            # the same camera in the affine frame
    return H, views, cams


def _rays(views, cams, noise_deg=0.0, rng=None, A=None):
    """Each camera's line of sight in the affine frame; with noise_deg, turned by that much
    (per axis, on the ground: A maps the affine frame to ENU)."""
    rays = []
    for k, (v, M) in enumerate(zip(views, cams)):
        d = tile_sight(M)
        if noise_deg:
            u = A @ d
            u = u / np.linalg.norm(u) + np.radians(noise_deg) * rng.normal(0, 1, 3)
            d = np.linalg.solve(A, u)
            d /= np.linalg.norm(d)
        rays.append(ViewRay(f"img_{k}", d, view_direction(v), np.zeros(3), 1))
    return rays


def _points(rng, H, n, relief_m):
    enu = np.c_[rng.uniform(-300, 300, (n, 2)), rng.normal(0, relief_m, n)] if relief_m else \
        np.c_[rng.uniform(-300, 300, (n, 2)), np.zeros(n)]
    return enu, apply_affine_3d(np.linalg.inv(H), enu)


def _cp(Xa, Xe, sigma_m=0.02):
    n = len(Xa)
    return ControlPoints(Xa, Xe, np.full((n, 3, 3), np.nan), np.full(n, sigma_m))


def _scale_error(H, H_true):
    D = H[:3, :3] @ np.linalg.inv(H_true[:3, :3])
    return D[2, 2] - 1.0


def test_coplanar_gcps_and_the_images_recover_the_height_scale():
    """Four GCPs exactly on one plane fix nothing of the height scale; the images' lines of sight
    fix it exactly (noise-free), and three GCPs not on one line do as well."""
    rng = np.random.default_rng(0)
    H, views, cams = _truth(rng)
    enu, aff = _points(rng, H, 4, 0.0)
    rays = _rays(views, cams)
    alone = fit_held(_cp(aff, enu), [])
    assert not alone.cov.determined
    assert not np.isfinite(looseness(alone.H, alone.cov).height_scale)
    held = fit_held(_cp(aff, enu), rays)
    np.testing.assert_allclose(held.H, H, atol=1e-6 * np.abs(H).max())
    three = fit_held(_cp(aff[:3], enu[:3]), rays)
    np.testing.assert_allclose(three.H, H, atol=1e-6 * np.abs(H).max())
    assert max(held.view_residual_deg.values()) < 1e-6


def test_noisy_sights_hold_the_height_scale_and_their_sigma_is_estimated():
    """0.1 degree of noise on 12 images' lines of sight: the height scale of 4 nearly coplanar
    GCPs (0.5 m off their plane, 0.3 m of noise) comes within the fit's own figure, far better
    than the GCPs alone, and the images' sigma is estimated from the residuals."""
    rng = np.random.default_rng(1)
    H, views, cams = _truth(rng, 12)
    errs, alone_errs, sig = [], [], []
    for trial in range(20):
        enu, aff = _points(rng, H, 4, 0.5)
        obs = enu + rng.normal(0, 0.3, enu.shape)
        pts = _cp(aff, obs, 0.3)
        held = fit_held(pts, _rays(views, cams, 0.1, rng, H[:3, :3]))
        alone = fit_held(pts, [])
        lo_h, lo_a = looseness(held.H, held.cov), looseness(alone.H, alone.cov)
        assert lo_h.height_scale < 0.2 * lo_a.height_scale
        errs.append(_scale_error(held.H, H) / lo_h.height_scale)
        alone_errs.append(abs(_scale_error(alone.H, H)))
        sig.append(held.sigma_view_deg)
    assert np.sqrt(np.mean(np.square(errs))) < 2.0          # the figure is honest (in sigmas)
    assert np.median(alone_errs) > 0.05                       # the GCPs alone: 5 % and more
    assert 0.06 < np.median(sig) < 0.15                       # ~0.1 deg, from 12 images' residuals


def test_the_images_vertical_is_turned_into_the_sites_frame():
    """A line of sight stated at a ground point 20 km east of the frame's origin is turned by
    the vertical's change there (about 3e-3 rad)."""
    frame = LocalFrame(10.0, 45.0, 0.0)
    lon, lat = frame.enu_to_geodetic(np.array([[20_000.0, 0.0, 0.0]]))[0, :2]
    v_local = view_direction(ViewAngles(0.0, 0.0))          # straight up there
    ray = ViewRay("a", np.array([0.0, 0.0, 1.0]), v_local, np.array([20_000.0, 0.0, 0.0]), 1)
    v = ray.direction(frame, np.eye(4))
    expected = frame.R @ enu_rotation(float(lon), float(lat)).T @ v_local
    np.testing.assert_allclose(v, expected, atol=1e-12)
    assert 2.5e-3 < np.arccos(v[2]) < 3.5e-3
    assert np.array_equal(ray.direction(), v_local)


def _inputs(H, enu, aff, roles=None):
    roles = roles or ["control"] * len(enu)
    return [GcpInput(f"G{k}", r, aff[k], enu[k], sigma_m=0.02) for k, r in enumerate(roles)]


def test_upgrade_with_three_gcps_and_a_wrong_view_left_out():
    """upgrade(): 3 control GCPs held by the images are enough, coplanar GCPs are no longer
    refused; an image whose view is its elevation (90 - incidence) is left out, named."""
    rng = np.random.default_rng(2)
    H, views, cams = _truth(rng, 5)
    enu, aff = _points(rng, H, 8, 0.0)
    rays = _rays(views, cams)
    res = upgrade(_inputs(H, enu, aff, ["control"] * 3 + ["check"] * 5), hold=ImageHold(rays))
    assert res.n_control_used == 3 and res.views["images"] == 5 and res.dof == 3 * 3 - 12 + 10
    assert res.stats["check"]["rmse_3d_m"] < 1e-3
    with pytest.raises(ReconstructionError, match="3 when the images' viewing angles are known"):
        upgrade(_inputs(H, enu, aff, ["control"] * 3 + ["check"] * 5))
    bad = list(views)
    bad[1] = ViewAngles(90.0 - views[1].incidence_deg, views[1].azimuth_deg)
    res = upgrade(_inputs(H, enu, aff, ["control"] * 4 + ["check"] * 4),
                  hold=ImageHold(_rays(bad, cams)))
    assert res.views["images"] == 4 and "img_1" not in res.views["residual_deg"]
    assert any("img_1" in w and "elevation" in w for w in res.warnings)
    assert res.stats["check"]["rmse_3d_m"] < 1e-3


def test_collinear_gcps_are_refused_even_with_the_images():
    rng = np.random.default_rng(3)
    H, views, cams = _truth(rng, 4)
    t = np.linspace(-1, 1, 5)[:, None]
    enu = t * np.array([[200.0, 100.0, 0.0]])
    aff = apply_affine_3d(np.linalg.inv(H), enu)
    with pytest.raises(ReconstructionError, match="collinear"):
        upgrade(_inputs(H, enu, aff), hold=ImageHold(_rays(views, cams)))


def test_the_check_point_that_would_help_most_is_named():
    """GCPs alone on flat ground: the report names the check point off their plane as the one
    that, as a control point, would bring the expected height error down most."""
    rng = np.random.default_rng(4)
    H, _, _ = _truth(rng)
    enu, _ = _points(rng, H, 6, 0.0)
    enu[:4, 2] = [0.3, -0.3, 0.2, -0.2]
    enu[4, 2] = 25.0                                       # a roof
    aff = apply_affine_3d(np.linalg.inv(H), enu)
    res = upgrade(_inputs(H, enu, aff, ["control"] * 4 + ["check"] * 2))
    c = res.conditioning
    assert c["best_next_gcp"]["id"] == "G4"
    assert c["best_next_gcp"]["expected_height_error_m"] < 0.2 * c["expected_height_error_m"]
    assert any("G4, now a check point" in w for w in res.warnings)


def test_gcps_nearly_on_one_line_leave_the_tilt_loose_and_say_so():
    """Three control GCPs 8 m off one line 400 m long: the tilt across it is loose; the report
    gives the height error it leaves at the site's edge, and warns."""
    rng = np.random.default_rng(5)
    H, views, cams = _truth(rng, 5)
    enu = np.array([[-200.0, 0.0, 0.0], [0.0, 8.0, 0.0], [200.0, 0.0, 0.0]])
    aff = apply_affine_3d(np.linalg.inv(H), enu)
    site = apply_affine_3d(np.linalg.inv(H), np.c_[rng.uniform(-300, 300, (500, 2)), np.zeros(500)])
    gcps = [GcpInput(f"G{k}", "control", aff[k], enu[k], sigma_m=0.1) for k in range(3)]
    res = upgrade(gcps, hold=ImageHold(_rays(views, cams)), site_points=site)
    c = res.conditioning
    assert c["site_radius_m"] > 250 and c["expected_edge_error_m"] > 2.0
    assert c["expected_edge_error_m"] > 5 * c["expected_height_error_m"]
    assert any("nearly on one line" in w and "site's edge" in w for w in res.warnings)


def test_two_images_that_disagree_are_both_left_out():
    """With two images, one wrong view cannot be told from the other: both are left out, the
    GCPs alone fix H_A (4 of them, off one plane), and the warning names both."""
    rng = np.random.default_rng(6)
    H, views, cams = _truth(rng, 2)
    enu, aff = _points(rng, H, 8, 20.0)
    bad = [views[0], ViewAngles(90.0 - views[1].incidence_deg, views[1].azimuth_deg)]
    res = upgrade(_inputs(H, enu, aff, ["control"] * 4 + ["check"] * 4), hold=ImageHold(_rays(bad, cams)))
    assert res.views is None and any("img_0" in w and "img_1" in w for w in res.warnings)
    assert res.stats["check"]["rmse_3d_m"] < 1e-3
    with pytest.raises(ReconstructionError, match="img_1"):
        upgrade(_inputs(H, enu, aff, ["control"] * 3 + ["check"] * 5), hold=ImageHold(_rays(bad, cams)))
