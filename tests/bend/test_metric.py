"""The metric bend step (recon_core.bend.metric): the horizontal projective warp no
affine frame lets the views see is found once each image's 1D perspective is known by physics.

Render-free (recon_core.synthetic.wide_site): `large`'s 9 pushbroom cameras (orbits at 620-690
km) over 3.3 km, points on the true scene with 0.1 px of pixel noise. The truth is displaced by
the projective pair of the ground plane, X -> X (1 + a . X) (0.2 m RMS in E and in N after the
best affine map): the images see none of it through free pushbroom models, but do once the
models' depth term is fixed by the orbit."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.bend.pushbroom import BendWarp, estimate_bend, physical_depth
from recon_core.synthetic.wide_site import make_wide_site, structure_vs_truth


@pytest.fixture(scope="module")
def warped_site():
    site = make_wide_site("large", 0, n_points=6000, noise_px=0.1, d=1000)
    X = site.X_true
    images = site.views_per_image()
    c = X.mean(0)
    half = np.ptp(X[:, :2], 0).max() / 2
    D = np.zeros_like(X)
    D[:, :2] = (X[:, :2] - c[:2]) * (((X[:, :2] - c[:2]) / half) @ np.array([0.6, -0.4]))[:, None] / half
    return X, X + D, images


def _depth(X, images, altitude_m):
    out = []
    for pts, xy in images:
        P = np.linalg.lstsq(np.hstack([X[pts], np.ones((len(pts), 1))]), xy, rcond=None)[0].T
        out.append(physical_depth(P, altitude_m))
    return out


def _horizontal_rms(X, Xt) -> float:
    e, n, _ = structure_vs_truth(X, Xt)["rms_enu_m"]
    return float(np.hypot(e, n))


def test_the_projective_pair_is_found_only_with_the_physics(warped_site):
    X, Xb, images = warped_site
    assert _horizontal_rms(Xb, X) > 0.25
    # free depth terms (the affine frame's bend step): the warp stays
    w, info = estimate_bend(Xb, images)
    assert _horizontal_rms(Xb + w(Xb), X) > 0.25
    # the depth known from an orbit, horizontal displacements only, the common range free: every
    # horizontal warp at once, the focal plane's terms (a bowed, distorted line) take two of the
    # seven, and what is left does not hold the pair ...
    w, info = estimate_bend(Xb, images, depth=_depth(Xb, images, 694e3), range_free=True,
                            directions=np.eye(3)[:2])
    assert info["warps_seen"] == 5
    # ... the projective pair alone (what metric_bend estimates) is found, whatever the assumed
    # altitude within -20 %/+5 % of the truth's 620-690 km
    for alt, pair in ((550e3, np.eye(3)[:2]), (694e3, np.eye(3)[:2])):
        w, info = estimate_bend(Xb, images, depth=_depth(Xb, images, alt), range_free=True,
                                directions=np.eye(3)[:2], pair=pair)
        assert info["warps_seen"] == 3
        assert _horizontal_rms(Xb + w(Xb), X) < 0.03, alt
        assert np.abs(w(Xb)[:, 2]).max() < 1e-12              # no vertical displacement
        # the data's range: the assumed one corrected towards the truth's (~653 km on average)
        assert abs(alt / (1 + info["range_change"]) - 653e3) < 40e3


def test_rows_across_track_are_told_apart(warped_site):
    """Columns and rows swapped (the perspective then in the rows): the data's range change is
    near -1 (no perspective where the physics puts it), which metric_bend refuses (> 0.5)."""
    from recon_core.bend.metric import MAX_RANGE_CHANGE

    _, Xb, images = warped_site
    swapped = [(p, xy[:, ::-1]) for p, xy in images]
    _, info = estimate_bend(Xb, swapped, depth=_depth(Xb, swapped, 694e3), range_free=True,
                            directions=np.eye(3)[:2])
    assert info["range_change"] < -MAX_RANGE_CHANGE


def test_the_upgrade_map_applies_the_warp_then_h(tmp_path):
    from recon_core.geometry.enu_map import EnuMap, warp_record

    rng = np.random.default_rng(0)
    w = BendWarp(rng.normal(size=3), np.eye(3) + 0.1 * rng.normal(size=(3, 3)), rng.normal(size=(2, 3)),
                 rng.normal(size=3), 0.01 * rng.normal(size=9))
    H = np.vstack([rng.normal(size=(3, 4)), [0, 0, 0, 1]])
    m = EnuMap(H, w)
    X = rng.normal(size=(50, 3))
    np.testing.assert_allclose(m(X), (X + w(X)) @ H[:3, :3].T + H[:3, 3])
    back = EnuMap.from_record({"H": H.tolist(), "metric_warp": warp_record(w)})
    np.testing.assert_allclose(back(X), m(X), atol=1e-12)
    assert back.same(m) and not EnuMap(H).same(m)
    np.testing.assert_allclose(EnuMap.from_record({"H": H.tolist()})(X), X @ H[:3, :3].T + H[:3, 3])
