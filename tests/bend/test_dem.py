"""The vertical bend held by a coarse reference DEM (recon_core.bend.dem), against a
known scene: a 10 km site of terrain and buildings, its structure bent by a saddle of tens of
metres the way three views of one date leave it, 4 control GCPs near the centre, and a DEM of
1 arc-second cells with an offset, a tilt and correlated noise of metres."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from recon_core.bend.dem import fit_dem_bend, fit_surface, open_reference_dem
from recon_core.geometry.affine import apply_affine_3d, fit_affine_3d
from recon_core.geometry.geodesy import LocalFrame

HALF = 5000.0


def _ground(E, N):
    return 120.0 + 25.0 * np.sin(E / 1700.0) * np.cos(N / 2300.0) + 8e-4 * E


def _roofs(E, N):
    # blocks of 60 m with a building of 15 m on every third one
    k = (np.floor(E / 60.0) * 7 + np.floor(N / 60.0) * 13) % 3 == 0
    return 15.0 * k


def _write_dem(path, frame, *, noise_m=2.0, offset_m=25.0, tilt=2e-4, seed=0, corr_px=5.0):
    """A 1 arc-second DEM (EPSG:4326) of the scene: the ground plus the buildings' mean share,
    an offset, a tilt and correlated noise."""
    import rasterio
    from rasterio.transform import from_origin

    corners = frame.enu_to_geodetic(np.array([[-1.2 * HALF, -1.2 * HALF, 0], [1.2 * HALF, 1.2 * HALF, 0]]))
    d = 1.0 / 3600.0
    lon0, lat1 = corners[0, 0], corners[1, 1]
    w = int(np.ceil((corners[1, 0] - lon0) / d))
    h = int(np.ceil((lat1 - corners[0, 1]) / d))
    lon = lon0 + (np.arange(w) + 0.5) * d
    lat = lat1 - (np.arange(h) + 0.5) * d
    LON, LAT = np.meshgrid(lon, lat)
    enu = frame.geodetic_to_enu(np.stack([LON.ravel(), LAT.ravel(), np.zeros(LON.size)], 1))
    E, N = enu[:, 0], enu[:, 1]
    z = _ground(E, N) + 5.0 + offset_m + tilt * (E + N)
    rng = np.random.default_rng(seed)
    noise = ndimage.gaussian_filter(rng.standard_normal((h, w)), corr_px)
    z = z.reshape(h, w) + noise * noise_m / noise.std()
    with rasterio.open(path, "w", driver="GTiff", width=w, height=h, count=1, dtype="float32", crs="EPSG:4326",
                       transform=from_origin(lon0, lat1, d, d)) as dst:
        dst.write(z.astype(np.float32), 1)
    return path


def _scene(frame, n=60000, seed=1):
    """True ENU points (ellipsoidal heights of ground and roofs) and their structure in an
    affine frame, bent by a vertical saddle and a horizontal warp the DEM cannot see."""
    rng = np.random.default_rng(seed)
    E, N = rng.uniform(-HALF, HALF, (2, n))
    llh = frame.enu_to_geodetic(np.stack([E, N, np.zeros(n)], 1))
    llh[:, 2] = _ground(E, N) + _roofs(E, N)
    T = frame.geodetic_to_enu(llh)
    e, n_ = T[:, 0] / HALF, T[:, 1] / HALF
    bent = T + np.stack([1.5 * e * n_, -1.0 * e * e, 18.0 * e * e - 10.0 * e * n_ - 22.0 * n_ * n_], 1)
    bent += rng.normal(0, 0.3, bent.shape)
    A = np.array([[0.8, 0.3, 0.1, 40.0], [-0.2, 1.1, 0.05, -7.0], [0.25, -0.1, 0.6, 3.0], [0, 0, 0, 1.0]])
    X = apply_affine_3d(np.linalg.inv(A), bent)
    return T, X


def _control(T):
    """4 control GCPs 2 km from the centre, two on roofs and two on the ground (non-coplanar, as
    an operator picks them), among the points T."""
    roof = _roofs(T[:, 0], T[:, 1]) > 0
    return [int(np.argmin(np.hypot(T[:, 0] - x, T[:, 1] - y) + 1e6 * (roof != r)))
            for x, y, r in ((-1500, -1500, True), (1500, -1500, False), (1500, 1500, True), (-1500, 1500, False))]


def test_a_dem_takes_out_the_saddle_four_gcps_leave(tmp_path):
    frame = LocalFrame(30.0, 31.0, 120.0)
    T, X = _scene(frame)
    dem = open_reference_dem(_write_dem(tmp_path / "dem.tif", frame))
    ctrl = _control(T)
    H0 = np.eye(4)
    H0[:3] = fit_affine_3d(X[ctrl], T[ctrl])
    before = apply_affine_3d(H0, X) - T
    # the upgrade's fit, here a plain affine map, on the GCPs' surveyed positions less the bend
    fit = fit_dem_bend(H0, X, frame, dem, np.zeros(2), HALF,
                       lambda w: fit_affine_3d(X[ctrl], T[ctrl] - w(T[ctrl])))
    H, warp, info = fit.H, fit.warp, fit.summary
    assert info["applied"] and warp is not None and info["last_move_m"] < 0.01
    Y = apply_affine_3d(H, X)
    after = Y + warp(Y) - T
    rms_u = lambda r: float(np.sqrt(np.mean(r[:, 2] ** 2)))   # noqa: E731
    # the GCPs' affine map leaves the saddle, extrapolated: tens of metres at the edges
    assert rms_u(before) > 8.0
    # the saddle is found: 18 / -10 / -22 m of e^2, e n, n^2 in the structure, through the DEM's
    # 2 m noise, offset of 25 m and tilt of 1 m over the site
    np.testing.assert_allclose(info["bend_coef_m"], [-18.0, 10.0, 22.0], atol=1.0)
    # what is left in the heights is the 4 GCPs' affine map, extrapolated from their 3 km
    # square (their positions in the structure carry its 0.3 m noise), and that noise itself
    assert rms_u(after) < 1.5, rms_u(after)
    A = fit_affine_3d(Y + warp(Y), T)
    assert rms_u(apply_affine_3d(A, Y + warp(Y)) - T) < 0.5
    # the warp is vertical only, and the map puts the control GCPs where they were surveyed
    Yc = apply_affine_3d(H, X[ctrl])
    assert np.allclose(warp.coef[:6], 0) and np.abs(Yc + warp(Yc) - T[ctrl]).max() < 0.05
    # its standard error (a block bootstrap) covers what the 2 m of correlated noise leaves
    err = np.abs(np.array(info["bend_coef_m"]) - [-18.0, 10.0, 22.0]).max()
    assert 0.1 < info["bend_sigma_m"] < 1.0 and err < 3 * info["bend_sigma_m"]
    # the DEM's own offset is reported, not applied (it is the GCPs' to fix)
    assert abs(info["offset_m"] - 25.0) < 6.0


def test_without_a_bend_the_dem_changes_little_and_too_little_cover_is_refused(tmp_path):
    frame = LocalFrame(30.0, 31.0, 120.0)
    T, _ = _scene(frame)
    dem = open_reference_dem(_write_dem(tmp_path / "dem.tif", frame, seed=3))
    fit = fit_dem_bend(np.eye(4), T, frame, dem, np.zeros(2), HALF,
                       lambda w: fit_affine_3d(T[:50], T[:50] - w(T[:50])))
    warp, info = fit.warp, fit.summary
    d = warp(T)[:, 2]
    assert np.sqrt(np.mean(d ** 2)) < 0.5 and info["bend_range_m"] < 2.0
    # a structure of which the DEM sees only a corner: no bend is fitted from it
    r = dem.heights(*frame.enu_to_geodetic(T)[:, :2].T) - frame.enu_to_geodetic(T)[:, 2]
    corner = np.all(T[:, :2] > 2500, 1)
    r[~corner] = np.nan
    coef, why = fit_surface(T[:, 0], T[:, 1], r, np.zeros(2), HALF)
    assert coef is None and "covers" in why["reason"]


@pytest.mark.parametrize("max_read", [6000, 37])
def test_the_dem_is_sampled_where_it_is(tmp_path, monkeypatch, max_read):
    """A DEM that is a plane in lon and lat is sampled exactly (bilinear), read whole or
    decimated (a large DEM), to its last cell; outside it, NaN."""
    import rasterio
    from rasterio.transform import from_origin

    from recon_core.bend import dem as dem_bend

    monkeypatch.setattr(dem_bend, "MAX_READ_PX", max_read)
    d, lon0, lat0 = 1.0 / 3600.0, 30.0, 31.1
    w, h = 300, 200
    lon = lon0 + (np.arange(w) + 0.5) * d
    lat = lat0 - (np.arange(h) + 0.5) * d
    plane = lambda x, y: 100.0 + 3e4 * (x - lon0) - 5e4 * (y - lat0)   # noqa: E731  (8 m and -14 m per cell)
    with rasterio.open(tmp_path / "ramp.tif", "w", driver="GTiff", width=w, height=h, count=1, dtype="float64",
                       crs="EPSG:4326", transform=from_origin(lon0, lat0, d, d), nodata=-32768) as dst:
        dst.write(plane(*np.meshgrid(lon, lat)), 1)
    dem = open_reference_dem(tmp_path / "ramp.tif")
    # points in the middle of the raster: the window read is theirs, inside it, to its edges
    rng = np.random.default_rng(0)
    x = rng.uniform(lon[50], lon[250], 2000)
    y = rng.uniform(lat[160], lat[40], 2000)
    # decimated, GDAL averages blocks of a non-integer size: within 1 % of the plane's change
    # over a read pixel (~9 cells of 8 m)
    np.testing.assert_allclose(dem.heights(x, y), plane(x, y), atol=1e-6 if max_read > w else 0.7)
    assert np.isnan(dem.heights(np.array([lon0 - 0.01, lon0 + 1]), np.array([lat0 - 0.01, lat0 - 0.01]))).all()


def test_a_long_narrow_site_fully_covered_is_not_refused(tmp_path):
    """A 10 x 4 km strip that the DEM covers whole: its span is the strip's, not the square's."""
    frame = LocalFrame(30.0, 31.0, 120.0)
    T, _ = _scene(frame)
    strip = T[np.abs(T[:, 1]) < 2000]
    dem = open_reference_dem(_write_dem(tmp_path / "dem.tif", frame))
    llh = frame.enu_to_geodetic(strip)
    r = dem.heights(llh[:, 0], llh[:, 1]) - llh[:, 2]
    coef, info = fit_surface(strip[:, 0], strip[:, 1], r, np.zeros(2), HALF)
    assert coef is not None and info["span"] > 0.9, info


def test_the_upgrade_takes_the_bend_from_a_dem_only_where_the_views_cannot_see_it(tiny_run, tiny_site, tmp_path,
                                                                                   monkeypatch):
    """Through upgrade_models on `tiny`: a site of 0.2 km is not bent, the DEM is not applied and
    the map is the one without it; made to count as wide, the DEM's warp is applied, recorded
    where the DSM stage reads it, and the check points are no worse for it."""
    from aerec_viewer.results import outcome_markdown
    from recon_core.bend import dem as dem_bend
    from recon_core.bend import observability
    from recon_core.config import preset
    from recon_core.euclidean.upgrade_stage import upgrade_models
    from recon_core.geometry.enu_map import EnuMap
    from recon_core.synthetic.ref_dem import simulate_reference_dem

    state, _ = tiny_run
    # a DEM of 2 m cells: on a site of 0.2 km, what a DEM of 30 m is on 10 km
    dem = simulate_reference_dem(tiny_site / "gt_dsm.tif", tmp_path / "dem.tif", cell_m=2.0, noise_m=0.01,
                                 corr_m=30.0, arcsec=0.06)
    base = upgrade_models(state.gcps, state.models, preset("tiny"))
    cfg = preset("tiny").with_overrides({"upgrade.reference_dem": str(dem)})
    up = upgrade_models(state.gcps, state.models, cfg)
    assert not up.groups[0].dem_bend["applied"] and "too small to bend" in up.groups[0].dem_bend["reason"]
    np.testing.assert_array_equal(up.results[0].H, base.results[0].H)
    assert up.maps[0].enu_warp is None
    # as if it were wide (its views cannot see a vertical bend: test_georef_upgrade_stage)
    monkeypatch.setattr(observability, "BEND_WARN_WIDTH_KM", 0.0)
    monkeypatch.setattr(dem_bend, "CELL_M", 40.0)
    monkeypatch.setattr(dem_bend, "MIN_CELLS", 10)
    up = upgrade_models(state.gcps, state.models, cfg)
    info = up.groups[0].dem_bend
    assert info["applied"] and info["cells"] >= 10, info
    rec = up.groups[0].record()
    assert "dem_warp" in rec and "gcp_warp" not in rec and rec["dem_bend"]["applied"]
    back = EnuMap.from_record(rec)
    np.testing.assert_allclose(back.enu_warp.coef, up.maps[0].enu_warp.coef)
    assert np.allclose(back.enu_warp.coef[:6], 0.0)
    assert any("reference DEM dem.tif" in n for n in up.results[0].notes)
    assert not any("cannot see a bend" in w for w in up.results[0].warnings)
    c0, c1 = (u.results[0].stats["check"]["rmse_U_m"] for u in (base, up))
    assert c1 < c0 + 0.2, (c0, c1)
    # the viewer: its Results tab says so, and its Euclidean view applies the same warp
    out = _outcome(up)
    assert "height distortion taken from the reference DEM (dem.tif)" in outcome_markdown(out)
    assert out.transform(0).post is up.groups[0].enu_warp
    # a DEM of 10 m cells with 0.5 m of noise cannot tell a bend over 0.2 km of 40 m buildings:
    # refused with the fit's own standard error, and the warning that there is a bend is kept
    simulate_reference_dem(tiny_site / "gt_dsm.tif", tmp_path / "dem.tif", cell_m=10.0, noise_m=0.5,
                           corr_m=30.0, arcsec=0.3)
    monkeypatch.setattr(dem_bend, "CELL_M", 20.0)
    up = upgrade_models(state.gcps, state.models, cfg)
    assert not up.groups[0].dem_bend["applied"] and "the DEM tells its bend of" in up.groups[0].dem_bend["reason"]
    np.testing.assert_array_equal(up.results[0].H, base.results[0].H)
    assert any("the reference DEM could not" in w for w in up.results[0].warnings)
    assert "Reference DEM not used: the DEM tells its bend of" in outcome_markdown(_outcome(up))


def _outcome(up):
    from dataclasses import fields

    from aerec_viewer.results import UpgradeOutcome

    return UpgradeOutcome(**{f.name: getattr(up, f.name) for f in fields(up)})


def test_aerec_run_says_what_became_of_the_reference_dem(tiny_site, tmp_path, capsys):
    """`aerec run --reference-dem`: one line of the console says whether the DEM was used and
    why not; the report holds the same."""
    import json

    from recon_core.cli import main
    from recon_core.synthetic.ref_dem import simulate_reference_dem

    dem = simulate_reference_dem(tiny_site / "gt_dsm.tif", tmp_path / "srtm.tif", cell_m=10.0, arcsec=0.3)
    out = tmp_path / "out"
    assert main(["run", str(tiny_site), "--out", str(out), "--preset", "tiny", "--stage", "upgrade",
                 "--reference-dem", str(dem), "--reference-dem-degree", "3"]) == 0
    cap = capsys.readouterr()
    said = [ln for ln in (cap.out + cap.err).splitlines() if "reference DEM srtm.tif" in ln]
    assert len(said) == 1 and "not used (the site is" in said[0], said
    report = json.loads((out / "report.json").read_text())
    db = report["stages"]["upgrade"]["groups"]["0"]["dem_bend"]
    assert not db["applied"] and "too small to bend" in db["reason"]
    assert report["config"]["upgrade"]["reference_dem"] == str(dem.resolve())
    assert report["config"]["upgrade"]["reference_dem_degree"] == 3


def test_a_dem_replaced_in_place_makes_the_upgrade_stale(tiny_site, tmp_path):
    import os

    from recon_core.config import preset
    from recon_core.io.site import load_site
    from recon_core.resume import stage_hash
    from recon_core.synthetic.ref_dem import simulate_reference_dem

    dem = simulate_reference_dem(tiny_site / "gt_dsm.tif", tmp_path / "dem.tif", cell_m=10.0, arcsec=0.3)
    cfg = preset("tiny").with_overrides({"upgrade.reference_dem": str(dem)})
    site = load_site(tiny_site)
    before = {s: stage_hash(cfg, s, site) for s in ("sparse", "upgrade")}
    simulate_reference_dem(tiny_site / "gt_dsm.tif", dem, cell_m=10.0, arcsec=0.3, seed=5)
    os.utime(dem, ns=(1, 1))
    assert stage_hash(cfg, "upgrade", site) != before["upgrade"]
    assert stage_hash(cfg, "sparse", site) == before["sparse"]


def test_a_cubic_bend_needs_degree_three_and_a_dem_that_tells_it(tmp_path):
    """The structure bent by a saddle and a cubic (a pushbroom's bend over 10 km is not only
    quadratic): with upgrade.reference_dem_degree = 3 the DEM takes both out, the quadratic
    leaves the cubic, extrapolated. A cubic the DEM cannot tell falls back to the quadratic."""
    from recon_core.geometry.enu_map import EnuMap, EnuWarp

    frame = LocalFrame(30.0, 31.0, 120.0)
    T, X = _scene(frame)
    # and a cubic in its heights: 20 m of e^3 and -15 m of e n^2 at the edges (_scene's affine
    # frame: its linear part maps the vertical displacement)
    e, n = T[:, 0] / HALF, T[:, 1] / HALF
    L = np.linalg.inv(np.array([[0.8, 0.3, 0.1], [-0.2, 1.1, 0.05], [0.25, -0.1, 0.6]]))
    X0, X = X, X + np.outer(20.0 * e ** 3 - 15.0 * e * n * n, L[:, 2])
    dem = open_reference_dem(_write_dem(tmp_path / "dem.tif", frame))
    ctrl = _control(T)
    H0 = np.eye(4)
    H0[:3] = fit_affine_3d(X[ctrl], T[ctrl])
    rms, shape = {}, {}
    for degree in (2, 3):
        fit = fit_dem_bend(H0, X, frame, dem, np.zeros(2), HALF,
                           lambda w: fit_affine_3d(X[ctrl], T[ctrl] - w(T[ctrl])), degree=degree)
        H, warp, info = fit.H, fit.warp, fit.summary
        assert info["applied"] and info["degree"] == degree and warp.degree == degree
        assert len(warp.coef) == 3 * (3 if degree == 2 else 7) and np.allclose(warp.coef[:2 * len(warp.coef) // 3], 0)
        Y = apply_affine_3d(H, X)
        Z = Y + warp(Y)
        rms[degree] = float(np.sqrt(np.mean((Z - T)[:, 2] ** 2)))
        shape[degree] = float(np.sqrt(np.mean((apply_affine_3d(fit_affine_3d(Z, T), Z) - T)[:, 2] ** 2)))
        # the record gives the same map back (the DSM stage and the viewer read it)
        m = EnuMap(H, None, EnuWarp.from_record(warp.record()))
        np.testing.assert_allclose(m(X[:100]), Y[:100] + warp(Y[:100]))
    # the quadratic leaves the cubic's metres, which no affine map takes out; the cubic leaves
    # the structure's shape within 0.8 m of the truth (the points' 0.3 m, the DEM's 2 m over 150 m
    # cells), and the heights with the 4 GCPs' affine map extrapolated from their 3 km square
    assert shape[2] > 2.0 and shape[3] < 0.8, shape
    assert rms[2] > 3.0 and rms[3] < 0.4 * rms[2], rms
    # a DEM whose errors reach over kilometres does not tell a small cubic: the quadratic stays
    rng = np.random.default_rng(3)
    E, N = rng.uniform(-HALF, HALF, (2, 80000))
    f = ndimage.gaussian_filter(rng.standard_normal((100, 100)), 6)
    noise = f[((N + HALF) / 100).astype(int).clip(0, 99), ((E + HALF) / 100).astype(int).clip(0, 99)] / f.std()
    r = 1.5 * (E / HALF) ** 2 - (N / HALF) ** 2 + 1.5 * noise + rng.normal(0, 2, E.size)
    coef, info = fit_surface(E, N, r, np.zeros(2), HALF, degree=3)
    assert coef is not None and info["degree"] == 2 and len(coef) == 3
    assert info["degrees_refused"][0]["degree"] == 3 and info["degrees_refused"][0]["bend_sigma_m"] > 1.0
    # the same through fit_dem_bend, on the structure with the saddle alone: the rounds apply the
    # cubic asked for, the final structure's comparison refuses it (6 m of DEM error over ~1 km),
    # and it is redone as a quadratic
    dem = open_reference_dem(_write_dem(tmp_path / "dem_srtm.tif", frame, noise_m=6.0, corr_px=30.0))
    H0[:3] = fit_affine_3d(X0[ctrl], T[ctrl])
    fit = fit_dem_bend(H0, X0, frame, dem, np.zeros(2), HALF,
                       lambda w: fit_affine_3d(X0[ctrl], T[ctrl] - w(T[ctrl])), degree=3)
    H, warp, info = fit.H, fit.warp, fit.summary
    assert info["applied"] and info["degree"] == 2 and warp.degree == 2 and info["degree_asked"] == 3
    assert [r["degree"] for r in info["degrees_refused"]] == [3]


def test_a_dem_degree_without_a_dem_is_said_to_do_nothing(tiny_site, tmp_path, capsys):
    from recon_core.cli import main

    assert main(["run", str(tiny_site), "--out", str(tmp_path / "out"), "--preset", "tiny", "--stage", "sparse",
                 "--reference-dem-degree", "3", "--quiet"]) == 0
    assert "--reference-dem-degree has no effect without a reference DEM" in capsys.readouterr().err


def test_the_dem_degree_is_checked_before_any_compute():
    from recon_core.config import Config
    from recon_core.errors import InputError
    from recon_core.preflight import check_config

    check_config(Config().with_overrides({"upgrade.reference_dem_degree": 3}))
    with pytest.raises(InputError, match="reference_dem_degree"):
        check_config(Config().with_overrides({"upgrade.reference_dem_degree": 4}))
