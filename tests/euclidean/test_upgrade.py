"""Euclidean upgrade: H_A recovery, RANSAC, conditioning, residual report."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon_core.errors import ReconstructionError
from recon_core.euclidean.upgrade import (
    GcpInput,
    accuracy_stats,
    conditioning,
    fit_affine_upgrade,
    fit_upgrade_ransac,
    upgrade,
)
from recon_core.geometry.affine import apply_affine_3d as apply_h


def random_affine(rng: np.random.Generator) -> np.ndarray:
    """A well-conditioned random 4x4 affine map (ENU -> affine frame), in the style of a real one:
    anisotropic scale, shear, large translation."""
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    A = Q @ np.diag(rng.uniform(0.5, 3.0, 3)) @ (np.eye(3) + 0.3 * np.triu(rng.normal(size=(3, 3)), 1))
    M = np.eye(4)
    M[:3, :3] = A
    M[:3, 3] = rng.uniform(-1e3, 1e3, 3)
    return M


def scene(rng: np.random.Generator, n: int, relief_m: float = 60.0):
    """n surveyed points (ENU metres) spread over 1 km with `relief_m` of height, their affine
    positions, and the true H (affine -> ENU)."""
    enu = np.column_stack([rng.uniform(-500, 500, n), rng.uniform(-500, 500, n),
                           rng.uniform(0, relief_m, n)])
    M = random_affine(rng)                       # ENU -> affine
    aff = apply_h(M, enu)
    return enu, aff, np.linalg.inv(M)


def gcps_from(enu, aff, roles=None, **kw) -> list[GcpInput]:
    roles = roles or ["control"] * len(enu)
    return [GcpInput(id=f"G{i:02d}", role=r, affine_xyz=a, enu=e, **kw)
            for i, (e, a, r) in enumerate(zip(enu, aff, roles))]


def test_exact_recovery_from_four_points():
    rng = np.random.default_rng(1)
    enu, aff, H_true = scene(rng, 30)
    H = fit_affine_upgrade(aff[:4], enu[:4])
    assert np.allclose(H[3], [0, 0, 0, 1])
    rel = np.linalg.norm(H - H_true) / np.linalg.norm(H_true)
    assert rel < 1e-9
    # independent check: the 26 points not used map onto their surveyed positions
    assert np.abs(apply_h(H, aff[4:]) - enu[4:]).max() < 1e-6


def test_ransac_rejects_exactly_the_outliers():
    rng = np.random.default_rng(2)
    enu, aff, _ = scene(rng, 12)
    obs = enu + rng.normal(0, 0.2, enu.shape)
    bad = np.array([2, 7, 10])
    obs[bad] += rng.choice([-1, 1], (3, 3)) * rng.uniform(20, 50, (3, 3))
    H, inl = fit_upgrade_ransac(aff, obs, thresh_m=2.0, iters=1000, rng=np.random.default_rng(0))
    assert set(np.flatnonzero(~inl)) == set(bad)
    res = upgrade(gcps_from(aff=aff, enu=obs), ransac_thresh_m=2.0)
    rejected = {r["id"] for r in res.rejections}
    assert rejected == {f"G{i:02d}" for i in bad}
    assert all("RANSAC outlier" in r["reason"] for r in res.rejections)
    # the rejection is a warning (the console shows warnings even with --quiet), naming them
    w = [x for x in res.warnings if x.startswith("RANSAC rejected control GCP(s)")]
    assert len(w) == 1 and all(f"G{i:02d}" in w[0] for i in bad) and "m off" in w[0]
    assert res.n_control_used == 9 and res.dof == 3 * 9 - 12
    assert res.stats["control"]["rmse_3d_m"] < 0.6


def test_random_sampling_path_with_many_points():
    rng = np.random.default_rng(3)
    enu, aff, H_true = scene(rng, 40)
    obs = enu.copy()
    obs[:5, 2] += 30.0
    H, inl = fit_upgrade_ransac(aff, obs, thresh_m=1.0, iters=300, rng=np.random.default_rng(0))
    assert not inl[:5].any() and inl[5:].all()
    assert np.linalg.norm(H - H_true) / np.linalg.norm(H_true) < 1e-9


def test_exactly_coplanar_or_collinear_raises():
    rng = np.random.default_rng(4)
    enu, aff, _ = scene(rng, 6, relief_m=0.0)         # all at U = 0: exactly coplanar
    with pytest.raises(ReconstructionError, match="coplanar"):
        upgrade(gcps_from(enu, aff))
    t = np.linspace(0, 1, 5)[:, None]
    line = t * np.array([[100.0, 50.0, 10.0]])
    with pytest.raises(ReconstructionError, match="collinear"):
        upgrade(gcps_from(line, line * 2.0 + 1.0))


def test_nearly_coplanar_warns_with_expected_error_in_metres():
    rng = np.random.default_rng(5)
    enu, _, H_true = scene(rng, 6, relief_m=0.0)
    enu[:, 2] = rng.choice([-0.5, 0.5], 6)            # <= 0.5 m RMS off a plane
    aff = apply_h(np.linalg.inv(H_true), enu)
    res = upgrade(gcps_from(enu, aff))
    c = res.conditioning
    d = conditioning(enu)["plane_rms_m"]
    assert c["plane_rms_m"] == pytest.approx(d) and d < 0.51
    # before any fit (the pre-flight): sigma / d_rms on a 40 m structure, one point's figure
    assert conditioning(enu)["expected_height_error_m"] == pytest.approx(0.4 / d * 40.0, rel=1e-6)
    # after the fit: its covariance (0.4 m per axis for points without observations), which
    # averages over the 6 points: sigma / sqrt(sum of the squared distances off the plane),
    # give or take what the fit's other unknowns take
    off = (enu - enu.mean(0)) @ np.array(c["plane_normal"])
    assert c["basis"] == "fit" and c["gcp_only"]["expected_height_error_m"] == c["expected_height_error_m"]
    assert 0.99 <= c["expected_height_error_m"] / (0.4 / np.sqrt(np.sum(off ** 2)) * 40.0) < 1.3
    assert c["level"] == "poor"
    assert res.warnings and "m on a 40 m structure" in res.warnings[0]
    assert "off that plane" in res.warnings[0]
    # a set with real relief is fine: 0.4 / ~14 m * 40 m < 2 m
    enu2, _, _ = scene(np.random.default_rng(6), 12, relief_m=60.0)
    assert conditioning(enu2)["warning"] is None


def test_four_points_no_redundancy_and_check_points_are_only_scored():
    rng = np.random.default_rng(7)
    enu, aff, H_true = scene(rng, 8)
    roles = ["control"] * 4 + ["check"] * 4
    obs = enu.copy()
    obs[4:] += rng.normal(0, 0.5, (4, 3))             # check points with survey errors
    res = upgrade(gcps_from(obs, aff, roles, reproj_rms_px=0.3))
    assert res.dof == 0 and res.n_control_used == 4
    assert any("no redundancy" in n for n in res.notes)
    assert res.stats["control"]["rmse_3d_m"] < 1e-6    # zero by construction
    assert res.stats["check"]["n"] == 4
    expected = np.sqrt(np.mean((enu[4:] - obs[4:]) ** 2, axis=0))
    assert res.stats["check"]["rmse_E_m"] == pytest.approx(expected[0], rel=1e-6)
    # H without the check points is the same H
    res_ctrl = upgrade(gcps_from(obs[:4], aff[:4]))
    assert np.array_equal(res.H, res_ctrl.H)
    assert {p["status"] for p in res.points} == {"used", "check"}
    json.dumps(res.to_dict())


def test_check_points_never_change_h_with_ransac():
    rng = np.random.default_rng(8)
    enu, aff, _ = scene(rng, 14)
    obs = enu + rng.normal(0, 0.2, enu.shape)
    obs[12:] += 100.0                                 # wild check points
    base = upgrade(gcps_from(obs[:12], aff[:12]))
    full = upgrade(gcps_from(obs, aff, ["control"] * 12 + ["check"] * 2))
    assert np.array_equal(base.H, full.H)
    assert full.stats["check"]["rmse_E_m"] > 90


def test_leave_one_out_residuals():
    rng = np.random.default_rng(9)
    enu, aff, _ = scene(rng, 7)
    obs = enu + rng.normal(0, 0.3, enu.shape)
    res = upgrade(gcps_from(obs, aff))
    assert res.stats["loo"]["n"] == 7
    row = next(p for p in res.points if p["id"] == "G03")
    H = fit_affine_upgrade(np.delete(aff, 3, 0), np.delete(obs, 3, 0))   # independent refit
    r = apply_h(H, aff[3:4])[0] - obs[3]
    assert [row["loo_dE"], row["loo_dN"], row["loo_dU"]] == pytest.approx(list(r), abs=1e-9)
    # LOO residuals are larger than the fit residuals (they are prediction errors)
    assert res.stats["loo"]["rmse_3d_m"] > res.stats["control"]["rmse_3d_m"]
    four = upgrade(gcps_from(obs[:4], aff[:4]))
    assert "loo" not in four.stats and "loo_dE" not in four.points[0]


def test_ce90_le90_formulas():
    res = np.array([[1.0, 2.0, 3.0], [-1.0, -2.0, -3.0]])
    s = accuracy_stats(res)
    assert s["rmse_horizontal_m"] == pytest.approx(np.sqrt((1 + 4) / 2))
    assert s["ce90_m"] == pytest.approx(2.146 * np.sqrt(2.5))
    assert s["le90_m"] == pytest.approx(1.645 * 3.0)
    assert s["rmse_radial_m"] == pytest.approx(np.sqrt(5.0))


def test_unusable_gcps_and_too_few_controls():
    rng = np.random.default_rng(10)
    enu, aff, _ = scene(rng, 6)
    g = gcps_from(enu, aff)
    g[1].affine_xyz = None
    res = upgrade(g)
    row = next(p for p in res.points if p["id"] == "G01")
    assert row["status"] == "unusable" and "no affine position" in row["reason"]
    assert {"id": "G01", "reason": row["reason"]} in res.rejections
    g[2].affine_xyz = None
    g[3].affine_xyz = None
    with pytest.raises(ReconstructionError, match=r"only 3 usable control GCPs.*G01, G02, G03"):
        upgrade(g)


def test_a_disabled_gcp_is_left_out_of_the_fit_and_the_scores():
    rng = np.random.default_rng(12)
    enu, aff, H = scene(rng, 6)
    g = gcps_from(enu, aff)
    g[2].affine_xyz = g[2].affine_xyz + 50.0          # a gross blunder, disabled by the operator
    g[2].enabled = False
    res = upgrade(g)
    row = next(p for p in res.points if p["id"] == "G02")
    assert row["status"] == "unusable" and "disabled" in row["reason"]
    np.testing.assert_allclose(res.H, H, atol=1e-6 * np.abs(H).max())
    g[2].enabled = True                                 # enabled, the blunder enters the fit
    assert not np.allclose(upgrade(g, ransac_thresh_m=np.inf).H, H, atol=1e-3 * np.abs(H).max())


def test_apply_maps_affine_to_enu():
    rng = np.random.default_rng(11)
    enu, aff, _ = scene(rng, 10)
    res = upgrade(gcps_from(enu[:6], aff[:6]))
    assert np.abs(res.apply(aff) - enu).max() < 1e-6


def test_a_misclick_stands_out_among_good_clicks():
    """1.55 px of reprojection residual among clicks of 0.06-0.44 px is below the absolute 2 px
    threshold but flagged relative to the others; a uniformly mediocre set is not."""
    from aerec_viewer.results import residual_table_markdown

    rng = np.random.default_rng(7)
    enu, aff, _ = scene(rng, 6)
    gcps = gcps_from(enu, aff)
    for g, px in zip(gcps, [0.06, 0.2, 1.55, 0.44, 0.3, 0.15]):
        g.reproj_rms_px = px
    res = upgrade(gcps)
    flagged = [p["id"] for p in res.to_dict()["points"] if p.get("reproj_suspect")]
    assert flagged == ["G02"]
    assert any(w.startswith("GCP G02: reprojection residual 1.55 px") for w in res.warnings)
    assert "**G02** ⚠" in residual_table_markdown(res.to_dict())
    for g in gcps:
        g.reproj_rms_px = 0.6 + 0.05 * int(g.id[1:])
    assert not any(p.get("reproj_suspect") for p in upgrade(gcps).to_dict()["points"])


def test_a_blunder_among_five_controls_is_flagged_as_ambiguous_and_by_the_check_points():
    """5 control GCPs, one with a 25 m height blunder: any 4 of them fit exactly, so the sample
    with the blunder and the sample without it tie; the report must say so (naming both), and
    when the fit took the wrong one the check points, 17 m off in the trial that found this,
    must raise a warning rather than pass in silence."""
    rng = np.random.default_rng(21)
    enu, aff, H = scene(rng, 9)
    g = gcps_from(enu, aff, roles=["control"] * 5 + ["check"] * 4)
    g[2].enu = g[2].enu + np.array([0.0, 0.0, 25.0])
    res = upgrade(g)
    amb = [w for w in res.warnings if "cannot tell which control GCP" in w]
    rejected = {p["id"] for p in res.points if p["status"] == "rejected"}
    assert len(amb) == 1 and "G02" in amb[0] and rejected and all(r in amb[0] for r in rejected), res.warnings
    check_rmse = res.stats["check"]["rmse_3d_m"]
    if "G02" in rejected:                               # the right choice: check points agree
        assert check_rmse < 1e-6
    else:
        assert any("check points are off by" in w and "RMS (3D), more than" in w for w in res.warnings)
    # no blunder: no ambiguity and no check-point warning
    g[2].enu = enu[2]
    assert not [w for w in upgrade(g).warnings if "cannot tell" in w or "check points are off" in w]


def test_no_ambiguity_warning_with_many_noisy_controls_and_one_blunder():
    """12 control GCPs with 0.3 m noise and one 25 m blunder: RANSAC's choice is clear (swapping
    the blunder for a good point costs far more), so no "cannot tell" warning."""
    rng = np.random.default_rng(22)
    enu, aff, H = scene(rng, 12)
    g = gcps_from(enu + rng.normal(0, 0.3, enu.shape), aff)
    g[5].enu = g[5].enu + np.array([0.0, 0.0, 25.0])
    res = upgrade(g)
    assert {p["id"] for p in res.points if p["status"] == "rejected"} == {"G05"}
    assert not [w for w in res.warnings if "cannot tell" in w], res.warnings
