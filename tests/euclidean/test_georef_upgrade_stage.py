"""GCPs into a group's affine frame, and the upgrade stage's one function, against a known map:
GCPs built from the tiny model's own points through a chosen H_A must give that H_A back."""

from __future__ import annotations

from dataclasses import replace

import json

import numpy as np
import pytest

from recon_core.config import preset
from recon_core.errors import ReconstructionError
from recon_core.euclidean.georef import triangulate_gcp
from recon_core.euclidean.upgrade_stage import upgrade_models
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import GCP

H_TRUE = np.array([[0.9, 0.2, 0.1, 30.0], [-0.15, 1.1, 0.05, -12.0], [0.3, -0.2, 2.5, 7.0], [0, 0, 0, 1.0]])


def _points(model, k: int, rng) -> np.ndarray:
    ids = model.point_ids()
    X = model.X[ids]
    # well spread, non-coplanar: extremes of the cloud along random directions
    dirs = rng.normal(size=(k, 3))
    return np.array([X[np.argmax(X @ d)] for d in dirs])


def test_triangulated_gcp_is_the_point_its_observations_come_from(tiny_run):
    state, _ = tiny_run
    m = state.models[0]
    X = m.X[m.point_ids()[100]]
    obs = {}
    for t in np.flatnonzero(m.registered):
        tile = m.tiles[t]
        uv = m.camera(t).project(X[None])[0]
        if tile.image not in obs and tile.contains(uv[None], margin=1.0)[0]:
            obs[tile.image] = tuple(uv)
    assert len(obs) >= 2
    a = triangulate_gcp(m, obs)
    assert a.source == "triangulated" and a.n_images == len(obs)
    # every tile of an image containing the pixel takes part; overlapping tiles' cameras of one
    # image agree to a few hundredths of a pixel (the frame's unit is about a pixel)
    assert np.abs(a.xyz - X).max() < 0.05 and a.reproj_rms_px < 0.05
    one = triangulate_gcp(m, dict(list(obs.items())[:1]))
    assert one.xyz is None and "needs >= 2" in one.source


def test_upgrade_models_recovers_a_known_map_from_picked_positions(tiny_run):
    state, _ = tiny_run
    m = state.models[0]
    rng = np.random.default_rng(0)
    Xa = _points(m, 6, rng)
    frame = LocalFrame(30.0, 31.2, 40.0)
    enu = Xa @ H_TRUE[:3, :3].T + H_TRUE[:3, 3]
    llh = frame.enu_to_geodetic(enu)
    gcps = [GCP(f"P{k}", *llh[k], role="control", affine_picked={0: Xa[k]}) for k in range(6)]
    # the frame is at the control GCPs' centroid: express the truth in that frame. H_TRUE is
    # not a metric map (the cameras' rows are not orthogonal through it): GCPs only, and no
    # metric bend step (its physics needs the metric frame); the picks are exact here, the
    # expected errors (for picks of 0.4 m) are not this test's subject
    cfg = preset("tiny").with_overrides({"upgrade.metric_prior_sigma_cos": 0.0, "upgrade.metric_bend": False,
                                         "upgrade.allow_flat_gcps": True})
    up = upgrade_models(gcps, {0: m}, cfg)
    Xe = up.frame.geodetic_to_enu(llh)
    np.testing.assert_allclose(up.results[0].apply(Xa), Xe, atol=1e-5)
    rec = up.groups[0].record()
    assert all(v["source"] == "picked" for v in rec["gcp_affine"].values()) and rec["gsd_m"] > 0
    # without positions for this group (picked on another group's cloud), nothing is placeable
    for g in gcps:
        g.affine_picked = {1: g.affine_picked[0]}
    with pytest.raises(ReconstructionError, match="group 0"):
        upgrade_models(gcps, {0: m}, cfg)


def test_the_upgrade_says_what_the_views_can_see_of_a_bend(tiny_run):
    """The report's bend observability: `tiny`'s 3 views of one date cannot see a vertical warp
    (as the render-free harness finds on `flat`), but a site of a few hundred metres is not
    warned about; the same figures over a site of kilometres are."""
    from recon_core.bend.metric import warped_model
    from recon_core.bend.observability import BEND_INVISIBLE_PX_PER_M, bend_observability, bend_warning

    state, _ = tiny_run
    rec = json.loads((state.layout.root / "report.json").read_text())["stages"]["upgrade"]["groups"]["0"]
    b = rec["bend_observability"]
    # of the structure the upgrade maps: after the metric bend step, when it applied one
    maps, _ = state.upgrade
    m = state.models[0] if maps[0].warp is None else warped_model(state.models[0], maps[0].warp)
    bv = bend_observability(m, np.array(rec["H"]))
    assert b == bv.to_dict()
    assert b["views"] == 3 and b["site_width_km"] < 1.0
    # its weakest warp is vertical and invisible (its relief, 40 m over 200 m, shows others)
    assert b["invisible_warps"] >= 1 and b["weakest_vertical_px_per_m"] < BEND_INVISIBLE_PX_PER_M
    assert b["vertical_share"][-1] > 0.8
    assert bend_warning(bv) is None and not any("cannot see a bend" in w for w in rec["warnings"])
    wide = bv.with_width(2.5)
    assert "cannot see a bend" in bend_warning(wide) and "2.5 km" in bend_warning(wide)
    assert bend_warning(replace(wide, weakest_vertical_px_per_m=0.006)) is None   # `large`'s 9 views
    # 4 control GCPs cannot fit the invisible warps (recon_core.bend.gcp): said, none applied
    gb = rec["gcp_bend"]
    assert not gb["applied"] and gb["control_gcps"] == 4 and "needed" in gb["reason"]
    assert maps[0].enu_warp is None and "gcp_warp" not in rec


def test_the_metric_bend_step_is_recorded_and_applied(tiny_run):
    """The upgrade record says what the metric bend step did (recon_core.bend.metric),
    and the map the DSM stage applies (read back from the record) is the upgrade's. On `tiny`
    (0.2 km) the orbit's range is not seen (the perspective moves its pixels by a few
    thousandths of a pixel), so the step can only move the structure by millimetres; rows
    across track are told apart on a wide site (tests/bend/test_metric.py)."""
    from recon_core.io.models import load_upgrade

    state, _ = tiny_run
    rec = json.loads((state.layout.root / "report.json").read_text())["stages"]["upgrade"]["groups"]["0"]
    mb = rec["metric_bend"]
    assert mb["images"] == 3 and "applied" in mb
    maps, _ = load_upgrade(state.layout)
    assert (maps[0].warp is not None) == mb["applied"] == ("metric_warp" in rec)
    m = state.models[0]
    X = m.X[m.point_ids()]
    np.testing.assert_allclose(maps[0](X), state.upgrade[0][0](X))
    if mb["applied"]:
        assert mb["warp_max_m"] < 0.05
        moved = np.linalg.norm(maps[0](X) - (X @ maps[0].H[:3, :3].T + maps[0].H[:3, 3]), axis=1)
        np.testing.assert_allclose(moved.max(), mb["warp_max_m"], rtol=1e-3)   # (H before its refit)


def test_a_metric_warp_goes_through_the_upgrade_its_record_and_the_dsm(tiny_run, monkeypatch, tmp_path):
    """When the metric bend step applies a warp (forced here: `tiny` is too small for the views
    to see the orbit's range), H_A is refitted on the warped structure, the record holds the warp,
    the map read back is the same, and the DSM stage puts the points where that map does."""
    from recon_core.bend.result import BendFit
    from recon_core.euclidean import upgrade_stage
    from recon_core.euclidean.dsm_stage import make_dsm
    from recon_core.euclidean.georef import enu_to_output, output_epsg
    from recon_core.euclidean.upgrade_stage import upgrade_models
    from recon_core.geometry.enu_map import BendWarp, EnuMap
    from recon_core.io.layout import OutLayout
    from recon_core.io.models import PointSource
    from recon_core.io.ply import read_ply

    state, _ = tiny_run
    m = state.models[0]
    X = m.X[m.point_ids()]
    c = X.mean(0)
    half = float(np.ptp(X, 0).max())
    # a pure quadratic warp in the frame's first axis, 1 % of the site at its edge
    warp = BendWarp(c, np.eye(3) / half, np.eye(3)[:2], np.zeros(3),
                    np.array([0.01, 0.0, 0.0, 0, 0, 0, 0, 0, 0]))
    assert np.abs(warp(X)).max() > 0.001 * half
    info = {"applied": True, "warps_seen": 3, "warp_rms_m": 0.0, "warp_max_m": 0.0}
    monkeypatch.setattr(upgrade_stage, "metric_bend", lambda *a, **k: BendFit(warp, dict(info)))
    up = upgrade_models(state.gcps, state.models, state.cfg)
    monkeypatch.setattr(upgrade_stage, "metric_bend", lambda *a, **k: BendFit(None, {"applied": False}))
    plain = upgrade_models(state.gcps, state.models, state.cfg)
    assert up.maps[0].warp is warp and plain.maps[0].warp is None
    assert not np.allclose(up.results[0].H, plain.results[0].H)        # refitted on the warped model
    rec = up.groups[0].record()
    back = EnuMap.from_record(rec)
    np.testing.assert_allclose(back(X), up.maps[0](X), atol=1e-9)
    H = np.array(rec["H"], dtype=np.float64)
    np.testing.assert_allclose(back(X), (X + warp(X)) @ H[:3, :3].T + H[:3, 3], atol=1e-9)
    # the DSM stage applies the whole map: its cloud equals the map's points in the output CRS
    lay = OutLayout(tmp_path)
    lay.root.mkdir(parents=True, exist_ok=True)
    cfg = state.cfg.with_overrides({"dsm.resolution_m": 1.0})
    pts = X[:500]
    make_dsm(state.site, {0: PointSource(pts, np.zeros(len(pts), np.uint8))}, {0: back}, up.frame, 0.5, cfg, lay)
    want = enu_to_output(back(pts), up.frame, output_epsg(state.site.hints, up.frame))
    got = read_ply(lay.cloud)[0]
    np.testing.assert_allclose(got, want, atol=1e-3)                # the same order: one group
