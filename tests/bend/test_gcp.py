"""The bend the views cannot see, fitted to control GCPs (recon_core.bend.gcp): the
true bend of a synthetic site is recovered from spread GCPs (checked on held-out points), and
nothing is applied from too few GCPs or where there is no bend to find."""

from dataclasses import replace

import numpy as np

from recon_core.bend.gcp import fit_gcp_bend
from recon_core.bend.observability import BendView
from recon_core.geometry.enu_map import EnuMap, EnuWarp


def _site(seed: int, n_ctrl: int, dome_m: float, noise_m: float = 0.05):
    """A 10 km site: an affine frame, its H_A, GCPs whose surveyed ENU positions carry a dome
    of `dome_m` at the edge in U paired with a horizontal shift (a warp of the invisible kind)."""
    rng = np.random.default_rng(seed)
    half, centre = 5000.0, np.array([120.0, -80.0])
    # the invisible warps as the views would give them: a U dome (e^2 + n^2) with 0.3 of it in E
    V = np.zeros((2, 9))
    V[0, [6, 8]] = 1.0                 # U e^2, U n^2
    V[0, [0, 2]] = 0.3                 # E e^2, E n^2
    V[0] /= np.linalg.norm(V[0])
    V[1, 7] = 1.0                      # U e n
    s = np.array([0.2, 0.1, 0.05, 5e-4, 1e-5])          # three seen, two not
    basis = np.vstack([np.eye(9)[[0, 4, 5]], V])
    obs = BendView(views=3, site_width_km=2 * half / 1000, singular_px_per_m=s.tolist(),
                   vertical_share=np.linalg.norm(basis[:, 6:], axis=1).tolist(), weakest_vertical_px_per_m=float(s[-1]),
                   invisible_warps=2, warps=basis.tolist(), centre_m=centre.tolist(), half_width_m=half)
    true = EnuWarp(centre, half, dome_m * np.linalg.norm(np.r_[1.0, 0.3, 1.0, 0.3]) * V[0] / 2.0)
    n = n_ctrl + 30
    Y = np.c_[rng.uniform(-half, half, (n, 2)) + centre, rng.uniform(20, 60, n)]
    Xe = Y + true(Y)                                      # surveyed
    H = np.eye(4)
    H[:3, :3] = np.array([[0.9, 0.1, 0.0], [-0.05, 1.1, 0.02], [0.01, 0.0, 0.7]])
    H[:3, 3] = [10.0, -4.0, 2.0]
    Xa = np.linalg.solve(H[:3, :3], (Y - H[:3, 3]).T).T    # the affine frame's points
    # H_A as fitted on the bent GCPs: the least-squares affine map from Xa to Xe
    A = np.c_[Xa[:n_ctrl], np.ones(n_ctrl)]
    H_fit = np.eye(4)
    H_fit[:3] = np.linalg.lstsq(A, Xe[:n_ctrl] + rng.normal(0, noise_m, (n_ctrl, 3)), rcond=None)[0].T
    return H_fit, Xa, Xe + 0.0, obs, n_ctrl, rng


def _rms(r):
    return float(np.sqrt(np.mean(np.sum(r * r, axis=1))))


def test_spread_gcps_recover_the_invisible_bend():
    H, Xa, Xe, obs, n, rng = _site(0, 12, dome_m=20.0)
    noisy = Xe[:n] + rng.normal(0, 0.05, (n, 3))
    fit = fit_gcp_bend(H, Xa[:n], noisy, obs, 1e-3)
    Hn, warp, info, inl, loo = fit.H, fit.warp, fit.summary, fit.inliers, fit.loo
    assert info["applied"] and info["invisible_warps"] == 2 and inl.all() and loo.shape == (n, 3)
    before = _rms((np.c_[Xa[n:], np.ones(len(Xa) - n)] @ H.T)[:, :3] - Xe[n:])
    after = _rms(EnuMap(Hn, None, warp)(Xa[n:]) - Xe[n:])
    assert before > 5.0                      # 4-GCP-style affine map: metres off at the checks
    assert after < 0.3, (before, after)      # the warps fitted: at the GCPs' noise
    assert info["loo_rms_bend_m"] < 0.2 * info["loo_rms_affine_m"]


def test_too_few_gcps_or_no_bend_apply_nothing():
    H, Xa, Xe, obs, n, rng = _site(1, 5, dome_m=20.0)
    fit = fit_gcp_bend(H, Xa[:n], Xe[:n], obs, 1e-3)
    warp, info = fit.warp, fit.summary
    assert not fit.applied and warp is None and not info["applied"] and info["control_gcps_needed"] == 8
    assert "needed" in info["reason"]
    # no bend: the extra warps only fit noise, and the leave-one-out says so
    H, Xa, Xe, obs, n, rng = _site(2, 10, dome_m=0.0, noise_m=0.3)
    noisy = Xe[:n] + rng.normal(0, 0.3, (n, 3))
    fit = fit_gcp_bend(H, Xa[:n], noisy, obs, 1e-3)
    warp, info = fit.warp, fit.summary
    assert not fit.applied and warp is None and not info["applied"] and "leave-one-out" in info["reason"]
    # every warp seen: nothing to fit
    obs2 = replace(obs, singular_px_per_m=[0.2, 0.1, 0.05, 0.02, 0.01])
    assert fit_gcp_bend(H, Xa[:n], noisy, obs2, 1e-3).summary["reason"] == "the views see every quadratic warp"


def test_enu_map_record_round_trip():
    w = EnuWarp(np.array([1.0, 2.0]), 3000.0, np.arange(9.0))
    m = EnuMap(np.eye(4), None, w)
    back = EnuMap.from_record({"H": np.eye(4).tolist(), "gcp_warp": w.record()})
    X = np.random.default_rng(0).normal(0, 2000, (50, 3))
    np.testing.assert_allclose(back(X), m(X))
    assert back.same(m) and not EnuMap(np.eye(4)).same(m)


def test_the_report_is_rescored_with_the_bend_and_a_blunder_left_out():
    """Through upgrade.upgrade (whose affine RANSAC rejects good GCPs that the bend moved) and
    rescore_with_bend: every good control GCP used again, the blunder rejected, the check points scored by
    the map with the warps, and the affine fit's warnings replaced."""
    from recon_core.euclidean.upgrade import GcpInput, rescore_with_bend, upgrade

    H, Xa, Xe, obs, n, rng = _site(3, 12, dome_m=30.0)
    surveyed = Xe + rng.normal(0, 0.05, Xe.shape)
    surveyed[2] += [0.0, 0.0, 25.0]                       # a blunder among the control GCPs
    gcps = [GcpInput(f"G{i:02d}", "control" if i < n else "check", Xa[i], surveyed[i], None, 0.2)
            for i in range(len(Xa))]
    res = upgrade(gcps, rng=np.random.default_rng(0))
    assert sum(p["status"] == "rejected" for p in res.points) >= 2     # the bend breaks the affine fit
    assert any(w.startswith("RANSAC") for w in res.warnings)
    ctrl = [p["id"] for p in res.points if p["status"] in ("used", "rejected")]
    idx = [int(k[1:]) for k in ctrl]
    fit = fit_gcp_bend(res.H, Xa[idx], surveyed[idx], obs, 1e-3)
    Hn, warp, info, inl, loo = fit.H, fit.warp, fit.summary, fit.inliers, fit.loo
    assert info["applied"] and not inl[ctrl.index("G02")] and inl.sum() == n - 1
    used = [k for k, ok in zip(ctrl, inl) if ok]
    out = rescore_with_bend(res, Hn, warp, {g.id: g.affine_xyz for g in gcps}, {g.id: g.enu for g in gcps}, used,
                  ["G02"], dict(zip(used, loo)), info, 2.0)
    status = {p["id"]: p["status"] for p in out.points}
    assert status["G02"] == "rejected" and sum(v == "used" for v in status.values()) == n - 1
    assert out.stats["check"]["rmse_3d_m"] < 0.3 < 5.0 < res.stats["check"]["rmse_3d_m"]
    assert out.n_control_used == n - 1 and out.stats["loo"]["n"] == n - 1
    assert not any(w.startswith("RANSAC") for w in out.warnings)
    assert any("G02" in w for w in out.warnings) and [r["id"] for r in out.rejections] == ["G02"]
    assert res.H is not out.H and status != {p["id"]: p["status"] for p in res.points}
    assert out.conditioning["n"] == n - 1 and res.conditioning["n"] < n - 1   # of the GCPs it used


def test_the_results_tab_says_what_the_gcp_bend_did():
    """The viewer's Results tab: the warps fitted and how far they move the site, or why not."""
    from aerec_viewer.results import UpgradeOutcome, outcome_markdown
    from recon_core.euclidean.upgrade import GcpInput, upgrade
    from recon_core.euclidean.upgrade_stage import GroupUpgrade
    from recon_core.geometry.geodesy import LocalFrame

    H, Xa, Xe, obs, n, rng = _site(4, 12, dome_m=30.0)
    gcps = [GcpInput(f"G{i:02d}", "control" if i < n else "check", Xa[i], Xe[i], None, 0.2) for i in range(n + 3)]
    res = upgrade(gcps, rng=np.random.default_rng(0))
    fit = fit_gcp_bend(res.H, Xa[:n], Xe[:n], obs, 1e-3)
    warp, info = fit.warp, fit.summary
    out = UpgradeOutcome(LocalFrame(30.0, 31.0), groups={0: GroupUpgrade(res, {}, 0.5, bend=obs.with_width(10.0),
                                                                         enu_warp=warp, gcp_bend=info)})
    md = outcome_markdown(out)
    assert "distortion fitted to the control GCPs" in md and "each GCP left out is predicted" in md
    T = out.transform(0)
    assert T.post is warp
    refused = dict(info, applied=False, reason="only 5 of 12 control GCPs agree within 2 m with the warps, 8 needed")
    md = outcome_markdown(UpgradeOutcome(LocalFrame(30.0, 31.0), groups={0: GroupUpgrade(
        res, {}, 0.5, bend=obs.with_width(10.0), gcp_bend=refused)}))
    assert "distortion not fitted to the GCPs: only 5 of 12" in md


def test_check_points_off_by_a_bend_are_not_only_blamed_on_the_gcps():
    """4 control GCPs on a bent site: the check points are far off and the views cannot see the
    bend; the warning that blames a wrong GCP also names the bend."""
    from recon_core.euclidean.upgrade import GcpInput, upgrade
    from recon_core.euclidean.upgrade_stage import _warn_bend

    H, Xa, Xe, obs, n, rng = _site(5, 4, dome_m=30.0)
    gcps = [GcpInput(f"G{i:02d}", "control" if i < n else "check", Xa[i], Xe[i], None, 0.2) for i in range(n + 10)]
    res = upgrade(gcps, rng=np.random.default_rng(0))
    assert any(w.startswith("the check points are off by") for w in res.warnings)
    _warn_bend(res, replace(obs.with_width(10.0), weakest_vertical_px_per_m=1e-5, views=3),
               {"applied": False, "control_gcps_needed": 8, "invisible_warps": 6})
    off = [w for w in res.warnings if w.startswith("the check points are off by")]
    assert off and off[0].endswith("or the structure is bent (next warning)")
    assert "cannot see a bend" in res.warnings[-1] and "8 or more control GCPs" in res.warnings[-1]


def test_leave_one_out_and_consensus_predict_with_the_map_they_fit():
    """Every fit centres the heights on one value: an exact affine change of the height scale is
    predicted exactly for each point left out, and a blunder kilometres off does not move the
    consensus (review: the centre had followed each subset's mean height)."""
    from recon_core.bend.gcp import _consensus, _loo

    rng = np.random.default_rng(7)
    Y = np.c_[rng.uniform(-5000, 5000, (12, 2)), rng.uniform(0, 200, 12)]
    Xe = Y.copy()
    Xe[:, 2] = 1.02 * Y[:, 2] + 0.001 * Y[:, 0] + 3.0        # an affine correction, no bend
    warp = EnuWarp(np.zeros(2), 5000.0, np.zeros(9))
    V = np.zeros((1, 9))
    V[0, 8] = 1.0                                            # a U n^2 warp
    z0 = float(Y[:, 2].mean())
    assert np.abs(_loo(Y, Xe, warp, V[:0], z0)).max() < 1e-6
    assert np.abs(_loo(Y, Xe, warp, V, z0)).max() < 1e-6
    Yb = Y.copy()
    Yb[3, 2] += 1500.0                                       # a blunder in one affine height
    inl = _consensus(Yb, Xe, warp, V, 2.0, np.random.default_rng(0), float(Yb[:, 2].mean()))
    assert inl.sum() == 11 and not inl[3]
