"""The cameras' metric constraint in the upgrade, against a known Euclidean truth: satellite-like
affine cameras whose rows are orthogonal in metres (up to a small, random departure), seen in an
affine frame through a random map; GCPs on nearly flat land with noise."""

from __future__ import annotations

import numpy as np

from recon_core.euclidean.metric_prior import ImageRows, fit_with_metric_prior, row_cosines
from recon_core.euclidean.upgrade import GcpInput, fit_affine_upgrade, upgrade
from recon_core.geometry.affine import apply_affine_3d


def _random_affine(rng):
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    A = Q @ np.diag(rng.uniform(0.5, 3.0, 3)) @ (np.eye(3) + 0.3 * np.triu(rng.normal(size=(3, 3)), 1))
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = rng.uniform(-1e3, 1e3, 3)
    return M                                               # ENU -> affine


def _cameras(rng, n_images: int, tiles: int = 12, departure: float = 1e-3) -> list[np.ndarray]:
    """Per image, (tiles, 2, 3) linear parts in ENU metres: rows orthogonal to the view direction
    (10-25 deg off nadir, any azimuth), 0.5 m GSD, aspect 0.9-1.0, row cosine ~ departure."""
    out = []
    for _ in range(n_images):
        off, az = np.radians(rng.uniform(10, 25)), rng.uniform(0, 2 * np.pi)
        v = np.array([np.sin(off) * np.cos(az), np.sin(off) * np.sin(az), -np.cos(off)])
        a = np.cross(v, [0.0, 0.0, 1.0])
        a /= np.linalg.norm(a)
        b = np.cross(v, a)
        spin = rng.uniform(0, 2 * np.pi)
        r1 = np.cos(spin) * a + np.sin(spin) * b
        r2 = np.cross(v, r1)
        skew = rng.normal(0, departure)
        aspect = rng.uniform(0.9, 1.0)
        base = np.stack([r1, aspect * (r2 + skew * r1)]) / 0.5
        out.append(base[None] * (1 + 1e-4 * rng.normal(size=(tiles, 2, 1))))
    return out


def _setup(rng, relief_m: float, noise_m: float, n_images: int = 6):
    enu = np.column_stack([rng.uniform(-1500, 1500, 4), rng.uniform(-1500, 1500, 4),
                           rng.uniform(0, relief_m, 4)])
    M = _random_affine(rng)
    aff = apply_affine_3d(M, enu + rng.normal(0, noise_m, enu.shape))    # the GCPs' affine points
    Minv = np.linalg.inv(M[:3, :3])
    rows = [ImageRows(f"im{k}", C @ Minv) for k, C in enumerate(_cameras(rng, n_images))]
    return enu, aff, np.linalg.inv(M), rows


def _height_error(H, H_true, top=np.array([0.0, 0.0, 40.0]), base=np.zeros(3)) -> float:
    """Error of the height of a 40 m structure (top minus base) mapped through H."""
    xa = apply_affine_3d(np.linalg.inv(H_true), np.stack([top, base]))
    got = apply_affine_3d(H, xa)
    return float((got[0, 2] - got[1, 2]) - 40.0)


def test_true_frame_has_orthogonal_rows_and_a_wrong_height_scale_does_not():
    rng = np.random.default_rng(1)
    _, _, H_true, rows = _setup(rng, 5.0, 0.0)
    assert np.abs(row_cosines(H_true, rows)).max() < 5e-3
    squash = np.diag([1.0, 1.0, 0.97, 1.0]) @ H_true           # 3 % short in height
    assert np.abs(row_cosines(squash, rows)).max() > np.abs(row_cosines(H_true, rows)).max()


def test_flat_gcps_height_scale_is_fixed_by_the_cameras():
    """4 GCPs within 5 m of a plane over 3 km, 0.3 m noise: the GCP-only fit's error on a 40 m
    structure is metres; with the cameras' constraint it is a fraction of that."""
    rng = np.random.default_rng(7)
    e_gcp, e_prior = [], []
    for _ in range(30):
        enu, aff, H_true, rows = _setup(rng, 5.0, 0.3)
        e_gcp.append(abs(_height_error(fit_affine_upgrade(aff, enu), H_true)))
        H, _ = fit_with_metric_prior(aff, enu, 0.3, rows, 2e-3)
        e_prior.append(abs(_height_error(H, H_true)))
    assert np.median(e_gcp) > 1.0
    assert np.median(e_prior) < 0.25 * np.median(e_gcp)


def test_strong_gcps_are_not_pulled_away():
    """GCPs with 300 m of relief fix the height scale on their own: the constraint changes the
    height of a 40 m structure by centimetres, not more."""
    rng = np.random.default_rng(3)
    for _ in range(10):
        enu, aff, H_true, rows = _setup(rng, 300.0, 0.05)
        H0 = fit_affine_upgrade(aff, enu)
        H, _ = fit_with_metric_prior(aff, enu, 0.05, rows, 2e-3)
        assert abs(_height_error(H, H_true) - _height_error(H0, H_true)) < 0.05


def test_upgrade_report_with_the_constraint():
    rng = np.random.default_rng(5)
    enu, aff, H_true, rows = _setup(rng, 5.0, 0.3)
    gcps = [GcpInput(f"G{k}", "control", aff[k], enu[k]) for k in range(4)]
    plain = upgrade(gcps)
    res = upgrade(gcps, camera_rows=rows, sigma_cos=2e-3)
    assert plain.metric_prior is None and plain.dof == 0
    assert res.dof == len(rows)                               # 3N - 12 + one per image
    mp = res.metric_prior
    assert mp["images"] == len(rows) and set(mp["row_cosine"]) == {r.image for r in rows}
    assert max(map(abs, mp["row_cosine"].values())) < max(map(abs, mp["row_cosine_gcp_only"].values()))
    # the expected height error comes down with the constraint, and says so
    c0, c1 = plain.conditioning, res.conditioning
    assert c1["expected_height_error_m"] < 0.5 * c0["expected_height_error_m"]
    assert c1["gcp_only_expected_height_error_m"] == c0["expected_height_error_m"]
    assert abs(_height_error(res.H, H_true)) < abs(_height_error(plain.H, H_true))
    # N = 4 is no longer "zero by construction"
    assert any("metric constraint" in n for n in res.notes)
    assert max(abs(p["dU"]) for p in res.points) > 0
