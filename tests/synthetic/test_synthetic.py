"""Synthetic site generator: site format, pushbroom geometry, ray casting, GCPs, determinism.

Uses the `tiny` preset (3 images ~400 px) once per module and an even smaller preset for the
determinism check; the affine-error test is geometry only (no rendering)."""

from __future__ import annotations

import json
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.errors import NotGeoreferencedWarning

from recon_core.geometry.geodesy import geodetic_to_ecef
from recon_core.synthetic import generator as syn
from recon_core.synthetic.rpc import RPCModel
from recon_core.synthetic.scene_model import SceneModel

MICRO = replace(syn.PRESETS["tiny"], name="micro", groups=(2,), image_size=(160, 160),
                n_gcps=6)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny")
    stages = []
    truth = syn.generate_site(out, "tiny", seed=0,
                              progress=lambda s, d, t: stages.append((s, d, t)))
    return out, truth, stages


def _scene_with_accel(site: Path) -> SceneModel:
    scene = syn.load_truth_scene(site)
    hb = json.loads((site / "truth" / "scene.json").read_text())["height_bounds"]
    cams = syn.load_truth_cameras(site)
    pts = np.concatenate([scene.llh_to_local(c.footprint(h, 8))[:, :2]
                          for c in cams.values() for h in hb])
    (x0, y0), (x1, y1) = pts.min(0) - 20, pts.max(0) + 20
    scene.build_accel(x0, y0, x1, y1, 1.0)
    return scene


# ----------------------------------------------------------------------------------------
def test_site_layout(tiny):
    site, truth, stages = tiny
    names = sorted(p.name for p in (site / "images").iterdir())
    assert names == ["img_00.json", "img_00.tif", "img_01.json", "img_01.tif",
                     "img_02.json", "img_02.tif"]
    for f in ("gcps.geojson", "gt_dsm.tif", "site.json", "truth/cameras.json",
              "truth/rpc_fit.json", "truth/scene.json", "truth/images.json"):
        assert (site / f).exists(), f
    info = json.loads((site / "site.json").read_text())
    assert info["resolution_m"] == 0.5 and info["crs_epsg"] == truth.scene.epsg
    xmin, ymin, xmax, ymax = info["bounds"]
    assert xmax > xmin and ymax > ymin
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotGeoreferencedWarning)   # no warning spam
        for k in range(3):
            with rasterio.open(site / "images" / f"img_{k:02d}.tif") as ds:
                img = ds.read(1)
                assert ds.dtypes[0] == "uint16" and ds.count == 1
                assert ds.block_shapes[0] == (256, 256)
                assert img.max() <= 2047 and img.std() > 50
                tag = ds.tags()["TIFFTAG_DATETIME"]
                assert len(tag) == 19 and tag[4] == ":" and tag[10] == " "
                assert ds.rpcs is not None
            side = json.loads((site / "images" / f"img_{k:02d}.json").read_text())
            assert side["acquired"].endswith("Z")
            assert side["acquired"][:10].replace("-", ":") == tag[:10]
        with rasterio.open(site / "gt_dsm.tif") as ds:
            assert ds.dtypes[0] == "float32" and ds.nodata is not None
            assert ds.crs.to_epsg() == truth.scene.epsg and ds.res == (0.5, 0.5)
            assert tuple(ds.bounds) == tuple(info["bounds"])
            dsm = ds.read(1)
    valid = dsm != ds.nodata
    assert valid.mean() > 0.5
    assert dsm[valid].max() - dsm[valid].min() > 8.0   # buildings and trees
    seen = {s for s, _, _ in stages}
    assert {"cameras", "accel", "rpc", "gt_dsm", "gcps", "render img_00.tif"} <= seen


def test_gt_dsm_is_exact_height(tiny):
    site, truth, _ = tiny
    with rasterio.open(site / "gt_dsm.tif") as ds:
        dsm = ds.read(1)
        T = ds.transform
    rng = np.random.default_rng(0)
    r = rng.integers(0, dsm.shape[0], 300)
    c = rng.integers(0, dsm.shape[1], 300)
    ok = dsm[r, c] != -9999.0
    E = T.c + (c[ok] + 0.5) * T.a
    N = T.f + (r[ok] + 0.5) * T.e
    h = truth.scene.height_utm(E, N)
    assert np.abs(h - dsm[r[ok], c[ok]]).max() < 1e-3     # float32 storage


def test_dates_single_group(tiny):
    _, truth, _ = tiny
    dates = sorted(v["acquired"] for v in truth.images.values())
    from datetime import datetime
    d = [datetime.fromisoformat(x.replace("Z", "+00:00")) for x in dates]
    assert (d[-1] - d[0]).days < 15
    assert all(5.0 <= v["off_nadir_deg"] <= 30.5 for v in truth.images.values())


def test_rpc_fit_and_file_rpcs(tiny):
    site, truth, _ = tiny
    fit = json.loads((site / "truth" / "rpc_fit.json").read_text())
    assert fit["max_px"] < 0.05
    cams = syn.load_truth_cameras(site)
    rng = np.random.default_rng(1)
    for name, cam in cams.items():
        with rasterio.open(site / "images" / name) as ds:
            model = RPCModel.from_rasterio(ds.rpcs)
        cr = np.stack([rng.uniform(0, cam.width - 1, 200), rng.uniform(0, cam.height - 1, 200)], -1)
        llh = cam.localize(cr, rng.uniform(*truth.scene.height_bounds(), 200))
        assert np.abs(model.project(llh) - cr).max() < 0.05


def test_project_and_ray_are_inverse(tiny):
    site, truth, _ = tiny
    cam = syn.load_truth_cameras(site)["img_01.tif"]
    rng = np.random.default_rng(2)
    cr = np.stack([rng.uniform(-50, cam.width + 50, 300), rng.uniform(-50, cam.height + 50, 300)], -1)
    O, d = cam.ray(cr)
    # points along the rays project back to the pixel
    for s in (6.0e5, 7.0e5, 7.5e5):
        assert np.abs(cam.project_ecef(O + s * d) - cr).max() < 1e-6
    # ground points: the ray of their projection passes through them
    llh = cam.localize(cr, rng.uniform(20, 80, 300))
    X = geodetic_to_ecef(llh)
    O2, d2 = cam.ray(cam.project(llh))
    dist = np.linalg.norm(np.cross(X - O2, d2), axis=1)
    assert dist.max() < 0.01


def test_camera_dict_round_trip(tiny):
    site, truth, _ = tiny
    cams = syn.load_truth_cameras(site)
    for name, cam in cams.items():
        X = geodetic_to_ecef(cam.localize(np.array([[10.0, 20.0], [200.0, 300.0]]), 40.0))
        assert np.allclose(cam.project_ecef(X), truth.cameras[name].project_ecef(X), atol=1e-9)


def test_ray_casting_hits_surface(tiny):
    site, _, _ = tiny
    scene = _scene_with_accel(site)
    cam = syn.load_truth_cameras(site)["img_02.tif"]
    rng = np.random.default_rng(3)
    cr = np.stack([rng.uniform(0, cam.width - 1, 2000), rng.uniform(0, cam.height - 1, 2000)], -1)
    hits, st = syn.cast_pixels(cam, scene, cr)
    assert (st > 0).all()
    surf = st == 1
    assert surf.mean() > 0.7
    # surface hits lie on H; wall hits lie below the top of a discontinuity next to them
    h = scene.height(hits[surf, 0], hits[surf, 1])
    assert np.abs(h - hits[surf, 2]).max() < 0.01
    wall = ~surf
    if wall.any():
        x, y, z = hits[wall].T
        probe = np.max([scene.height(x + dx, y + dy) for dx, dy in
                        ((0.05, 0), (-0.05, 0), (0, 0.05), (0, -0.05))], axis=0)
        assert (probe > z + 0.01).all()
    # the camera sees every hit at its pixel
    uv = cam.project(scene.local_to_llh(hits))
    assert np.abs(uv - cr).max() < 1e-3


def test_column_interpolation_error(tiny):
    """Rays interpolated linearly between node columns (every 16 px) are exact to < 1 mm."""
    site, truth, _ = tiny
    scene = truth.scene
    cam = truth.cameras["img_00.tif"]
    lo, hi = scene.height_bounds()
    nodes = syn._node_cols(cam.width, 3)
    rows = np.array([10.25, 200.75, 380.25])
    top, bot = syn.block_segments(cam, scene, rows, nodes, hi + 0.05, lo - 0.5)
    cols = np.linspace(0.1, cam.width - 1.1, 97)
    for r_i, r in enumerate(rows):
        f = (cols - nodes[0]) / syn.NODE_STEP
        k = np.floor(f).astype(int)
        w = (f - k)[:, None]
        t_int = top[r_i, k] * (1 - w) + top[r_i, k + 1] * w
        b_int = bot[r_i, k] * (1 - w) + bot[r_i, k + 1] * w
        t_ex, b_ex = syn.ray_segments(cam, scene, np.stack([cols, np.full_like(cols, r)], -1),
                                      hi + 0.05, lo - 0.5)
        assert np.abs(t_int - t_ex).max() < 1e-3
        assert np.abs(b_int - b_ex).max() < 1e-3


def test_gcps(tiny):
    site, truth, _ = tiny
    fc = json.loads((site / "gcps.geojson").read_text())
    feats = fc["features"]
    assert 12 <= len(feats) <= 20
    roles = [f["properties"]["role"] for f in feats]
    assert roles.count("control") == 4 and roles.count("check") >= 8    # the method: 4 GCPs
    cams = syn.load_truth_cameras(site)
    rpcs = {}
    for name in cams:
        with rasterio.open(site / "images" / name) as ds:
            rpcs[name] = RPCModel.from_rasterio(ds.rpcs)
    errs, errs_rpc = [], []
    hs = []
    for f in feats:
        llh = np.array(f["geometry"]["coordinates"], dtype=float)
        obs = f["properties"]["observations"]
        assert len(obs) >= 2
        hs.append(llh)
        for name, (c, r) in obs.items():
            errs.append(np.hypot(*(cams[name].project(llh[None])[0] - (c, r))))
            errs_rpc.append(np.hypot(*(rpcs[name].project(llh[None])[0] - (c, r))))
    errs, errs_rpc = np.array(errs), np.array(errs_rpc)
    assert errs.max() < 1.5 and 0.15 < errs.mean() < 0.6
    assert errs_rpc.max() < 1.5
    # not coplanar: residual of the best plane through the control points > 1 m
    loc = truth.scene.llh_to_local(np.array(hs))
    ctl = np.array([r == "control" for r in roles])
    A = np.c_[loc[ctl, :2], np.ones(ctl.sum())]
    coef, *_ = np.linalg.lstsq(A, loc[ctl, 2], rcond=None)
    assert np.std(loc[ctl, 2] - A @ coef) > 1.0
    # both roof and ground points
    kinds = {g["kind"] for g in truth.gcps}
    assert kinds == {"roof", "ground"}


def test_parallax_between_views(tiny):
    """GCP positions in two images are not related by a 2D affine map: heights shift them
    differently (real parallax)."""
    _, truth, _ = tiny
    a, b = "img_00.tif", "img_01.tif"
    pa, pb = [], []
    for g in truth.gcps:
        o = g["true_observations"]
        if a in o and b in o:
            pa.append(o[a])
            pb.append(o[b])
    pa, pb = np.array(pa), np.array(pb)
    assert len(pa) >= 5
    A = np.c_[pa, np.ones(len(pa))]
    coef, *_ = np.linalg.lstsq(A, pb, rcond=None)
    resid = np.linalg.norm(A @ coef - pb, axis=1)
    assert resid.max() > 2.0
    # direct check: 20 m of height moves a point differently in the two views
    cams = truth.cameras
    llh = np.array([[truth.scene.lon0, truth.scene.lat0, truth.scene.h0],
                    [truth.scene.lon0, truth.scene.lat0, truth.scene.h0 + 20.0]])
    da = np.diff(cams[a].project(llh), axis=0)[0]
    db = np.diff(cams[b].project(llh), axis=0)[0]
    assert np.linalg.norm(da - db) > 5.0


def test_affine_error_vs_tile_size():
    """Geometry only: an 8000 px oblique image is not affine, its 1000 px tiles nearly are."""
    scene = SceneModel.create(0, 30.0, 31.2, 32.0)
    preset = syn.PRESETS["large"]
    acq = syn.design_acquisitions(preset, 0, scene.lat0, scene.lon0)[0]
    acq.size = (8000, 8000)
    acq.off_nadir = 28.0
    cam = syn.make_camera(acq, scene, preset, np.random.default_rng(0))
    err = syn.affine_error_vs_tile_size(cam, scene, sizes=(500, 1000, 2000), max_tiles=16)
    m = [err[s]["max_px"] for s in (500, 1000, 2000, "full")]
    assert m[0] < m[1] < m[2] < m[3]
    assert m[1] < 0.5
    assert m[3] > 1.0


def test_determinism(tmp_path):
    a = syn.generate_site(tmp_path / "a", MICRO, seed=5)
    b = syn.generate_site(tmp_path / "b", MICRO, seed=5)
    files = ["images/img_00.tif", "images/img_01.tif", "gt_dsm.tif", "gcps.geojson",
             "site.json", "truth/cameras.json"]
    for f in files:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f
    assert a.rpc_fit["max_px"] < 0.05 and b.bounds == a.bounds


def test_the_render_warmup_compiles_the_signature_the_renderer_uses():
    """The first `aerec view` compiles the render kernel in a second process on a stand-in
    context: its types must be a real scene's, or the warm-up compiles a signature nobody uses."""
    import numba

    from recon_core.synthetic.scene_model import SceneModel

    fake = syn.warm_render_kernel()
    real = SceneModel.create(0, 30.0, 31.2, 50.0).ctx
    assert [numba.typeof(v) for v in fake] == [numba.typeof(v) for v in real]


def test_synth_command_writes_whole_sites_only(tmp_path, monkeypatch, capsys):
    """`aerec synth` refuses a folder that holds anything (one line, exit 2, nothing written);
    an interrupted generation leaves neither the site nor its hidden partial folder; a finished
    one lands whole in a new or empty folder."""
    from recon_core.cli import main

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "img_05.tif").write_bytes(b"left over")
    assert main(["synth", str(busy), "--preset", "tiny", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("aerec: error:") == 1 and str(busy) in err and "not empty" in err
    assert [p.name for p in busy.iterdir()] == ["img_05.tif"]

    def interrupted(out, **kw):
        (Path(out) / "images").mkdir(parents=True)
        (Path(out) / "images" / "img_00.tif").write_bytes(b"half")
        raise KeyboardInterrupt

    monkeypatch.setattr(syn, "generate_site", interrupted)
    assert main(["synth", str(tmp_path / "cut"), "--preset", "tiny", "--quiet"]) == 130
    assert sorted(p.name for p in tmp_path.iterdir()) == ["busy"]

    def whole(out, **kw):
        (Path(out) / "images").mkdir(parents=True)
        (Path(out) / "site.json").write_text("{}")

    monkeypatch.setattr(syn, "generate_site", whole)
    empty = tmp_path / "empty"
    empty.mkdir()
    for out in (tmp_path / "new", empty):
        assert main(["synth", str(out), "--preset", "tiny", "--quiet"]) == 0
        assert sorted(p.name for p in out.iterdir()) == ["images", "site.json"]
    assert not list(tmp_path.glob(".*partial*"))
