"""Any 4 GCPs on a rendered site with bowed, distorted focal planes (`minifp`: 6 views of 800 px,
two dates): 4 control GCPs nearly on one plane, the images' viewing directions from their
sidecars, the height scale against the truth (the sparse structure's best affine map to its
true points, in evaluation only)."""

from __future__ import annotations

from dataclasses import replace
from itertools import combinations

import numpy as np
import pytest

from recon_core.config import preset
from recon_core.errors import ReconstructionError
from recon_core.euclidean.georef import frame_for
from recon_core.euclidean.upgrade_stage import upgrade_models
from recon_core.model.sparse_model import merge_joint
from recon_core.synthetic.truth import sparse_vs_truth


@pytest.fixture(scope="module")
def minifp(tmp_path_factory):
    from recon_core.events import EventBus
    from recon_core.pipeline import run
    from recon_core.synthetic.generator import generate_site

    root = tmp_path_factory.mktemp("minifp")
    generate_site(root / "site", preset="minifp", seed=0)
    state = run(root / "site", root / "out", preset("tiny"), until="sparse", bus=EventBus(lambda e: None))
    return state


def _flattest_four(gcps) -> set[str]:
    """The 4 GCPs nearest one plane among those spread over at least 30 % of the widest."""
    enu = frame_for(gcps).geodetic_to_enu(np.array([g.llh for g in gcps]))
    cands = []
    for q in combinations(range(len(gcps)), 4):
        X = enu[list(q)] - enu[list(q)].mean(0)
        cands.append((np.linalg.svd(X, compute_uv=False)[2], np.linalg.svd(X[:, :2], compute_uv=False)[1], q))
    wide = max(c[1] for c in cands)
    q = min((c for c in cands if c[1] >= 0.3 * wide), key=lambda c: c[0])[2]
    return {gcps[i].id for i in q}


def _widest_triangle(gcps):
    """(the GCPs' ENU positions, the 3 of them spanning the largest triangle in plan)."""
    enu = frame_for(gcps).geodetic_to_enu(np.array([g.llh for g in gcps]))

    def area(q):
        (a, b), (c, d) = enu[q[1], :2] - enu[q[0], :2], enu[q[2], :2] - enu[q[0], :2]
        return abs(a * d - b * c)
    return enu, max(combinations(range(len(enu)), 3), key=area)


def test_nearly_coplanar_gcps_get_the_true_height_scale_from_the_images(minifp):
    site, models = minifp.site, minifp.models
    assert all(im.view is not None for im in site.images)
    ctrl = _flattest_four(site.gcps)
    gcps = [replace(g, role="control" if g.id in ctrl else "check") for g in site.gcps]
    images = {im.name: im for im in site.images}
    up = upgrade_models(gcps, models, preset("tiny"), images)
    res = up.results[min(up.results)]
    assert res.conditioning["plane_rms_m"] < 0.1                      # the 4 lie on one plane
    model = merge_joint([models[g] for g in sorted(models)]) if up.joint else models[min(models)]
    A = np.asarray(sparse_vs_truth(site.root, model, up.frame)["A"])[:3, :3]
    D = res.H[:3, :3] @ np.linalg.inv(A)
    assert abs(D[2, 2] - 1.0) < 0.01                                  # the height scale within 1 %
    assert abs(D[0, 2]) < 0.01 and abs(D[1, 2]) < 0.01                # no shear of height into E, N
    assert res.views["images"] == 6 and res.conditioning["level"] == "ok"
    gcp_only = res.conditioning["gcp_only"]["expected_height_error_m"]
    assert gcp_only is None or gcp_only > 10 * res.conditioning["expected_height_error_m"]
    # the GCPs alone cannot: refused, and forced they are far off
    alone = preset("tiny").with_overrides({"upgrade.view_sigma_deg": 0.0})
    with pytest.raises(ReconstructionError, match="height scale"):
        upgrade_models(gcps, models, alone, images)
    forced = upgrade_models(gcps, models, alone.with_overrides({"upgrade.allow_flat_gcps": True}), images)
    D0 = forced.results[min(forced.results)].H[:3, :3] @ np.linalg.inv(A)
    assert abs(D0[2, 2] - 1.0) > 0.1


def test_three_gcps_and_the_images(minifp):
    """3 control GCPs, spread, with the images' viewing directions: the upgrade holds."""
    site, models = minifp.site, minifp.models
    enu, q = _widest_triangle(site.gcps)
    gcps = [replace(g, role="control" if k in q else "check") for k, g in enumerate(site.gcps)]
    up = upgrade_models(gcps, models, preset("tiny"), {im.name: im for im in site.images})
    res = up.results[min(up.results)]
    assert res.n_control_used == 3
    model = merge_joint([models[g] for g in sorted(models)]) if up.joint else models[min(models)]
    A = np.asarray(sparse_vs_truth(site.root, model, up.frame)["A"])[:3, :3]
    D = res.H[:3, :3] @ np.linalg.inv(A)
    assert abs(D[2, 2] - 1.0) < 0.01
    assert res.stats["check"]["rmse_U_m"] < 1.5


def test_a_height_known_worse_is_taken_from_the_images(minifp):
    """A control GCP whose height is 8 m off (a roof corner given the ground's height by a DEM)
    but says so (sigma_h_m): the images' lines of sight and the other GCPs fix the height scale,
    and its residual is the images' height for it; without sigma_h_m the error bends the fit."""
    site, models = minifp.site, minifp.models
    enu, q = _widest_triangle(site.gcps)
    q4 = q + (max((k for k in range(len(enu)) if k not in q),
                  key=lambda k: min(np.hypot(*(enu[k, :2] - enu[j, :2])) for j in q)),)
    wrong = site.gcps[q4[3]].id
    images = {im.name: im for im in site.images}

    def fit(sigma_h, off=8.0):
        gcps = [replace(g, role="control" if k in q4 else "check",
                        h=g.h - off if g.id == wrong else g.h,
                        sigma_h_m=sigma_h if g.id == wrong else None) for k, g in enumerate(site.gcps)]
        res = upgrade_models(gcps, models, preset("tiny"), images).results
        res = res[min(res)]
        checks = [p for p in res.points if p["role"] == "check" and p["dU"] is not None]
        return res, float(np.sqrt(np.mean([p["dU"] ** 2 for p in checks])))

    loose, u_loose = fit(4.0)
    tight, u_tight = fit(None)
    _, u_right = fit(None, off=0.0)
    print(f"check U RMSE: right {u_right:.3f} m; 8 m off with sigma_h 4 m {u_loose:.3f} m, without {u_tight:.3f} m")
    assert u_loose < 1.5 * u_right + 0.1 and u_tight > 5 * u_loose
    row = next(p for p in loose.points if p["id"] == wrong)
    assert row["sigma_h_m"] == 4.0 and abs(row["dU"] - 8.0) < 0.5      # the images' height: 8 m up
