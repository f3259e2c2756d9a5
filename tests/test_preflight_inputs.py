"""Every input checked in one pre-flight pass, before any compute: one line naming the file and
the problem, exit 2, nothing written; or, where the input can be used (float images with NaN
or infinite pixels), it is used with those pixels masked."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest
import rasterio

from recon_core.cli import main
from tests.conftest import write_tiff


def _run(site, tmp_path, *extra):
    return main(["run", str(site), "--out", str(tmp_path / "o"), "--quiet", *extra])


def _one_line(capsys, *words):
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("aerec: error:"), err
    for w in words:
        assert w in err[0], err
    return err[0]


@pytest.mark.parametrize("kind", ["fifo", "folder", "self-link", "dev-zero", "dangling"])
def test_a_name_of_images_that_is_not_an_image_file(kind, small_site, tmp_path, capsys):
    p = small_site / "images" / "c.tif"
    if kind == "fifo":
        os.mkfifo(p)
    elif kind == "folder":
        p.mkdir()
    elif kind == "self-link":
        p.symlink_to(p)
    elif kind == "dev-zero":
        p.symlink_to("/dev/zero")
    else:
        p.symlink_to(small_site / "images" / "gone.tif")
    for argv in (["run", str(small_site), "--out", str(tmp_path / "o"), "--quiet"], ["info", str(small_site)]):
        assert main(argv) == 2
        _one_line(capsys, "c.tif")
    assert not (tmp_path / "o").exists()


def _float_image(path, pattern: str, seed: int = 1):
    rng = np.random.default_rng(seed)
    a = rng.normal(100, 20, (96, 128)).astype(np.float32)
    if pattern == "rows":
        a[::8] = np.nan
    elif pattern == "inf":
        a[::2] = np.inf
    elif pattern == "all":
        a[:] = np.nan
    write_tiff(path, a)


@pytest.mark.parametrize("pattern", ["rows", "inf"])
def test_float_images_with_nan_or_inf_are_masked(pattern, tmp_path):
    from recon_core.io.site import load_site
    from recon_core.preflight import check_images
    from recon_core.sparse.features import group_tone_curves

    site = tmp_path / "s"
    _float_image(site / "images" / "a.tif", pattern)
    _float_image(site / "images" / "b.tif", "rows", seed=2)
    s = load_site(site)
    check_images(s)                                   # not blank, not refused
    curves, _ = group_tone_curves(s.images)
    assert all(np.isfinite([c.lo, c.hi]).all() and c.hi > c.lo for c in curves)
    assert main(["info", str(site)]) == 0


def test_an_all_nan_image_is_refused(tmp_path, capsys):
    site = tmp_path / "s"
    _float_image(site / "images" / "a.tif", "all")
    _float_image(site / "images" / "b.tif", "rows")
    assert _run(site, tmp_path, "--stage", "sparse") == 2
    _one_line(capsys, "a.tif", "is empty")


def test_two_identical_images_are_refused(small_site, tmp_path, capsys):
    shutil.copy(small_site / "images" / "a.tif", small_site / "images" / "c.tif")
    with rasterio.open(small_site / "images" / "c.tif", "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2020:01:04 10:00:00")
    assert _run(small_site, tmp_path, "--stage", "sparse") == 2
    _one_line(capsys, "c.tif", "same image as a.tif")
    assert not (tmp_path / "o").exists()


def test_a_product_too_large_is_refused_with_its_size(small_site, tmp_path, capsys):
    p = small_site / "images" / "huge.tif"
    with rasterio.open(p, "w", driver="GTiff", width=200_000, height=200_000, count=1, dtype="uint16",
                       tiled=True, BIGTIFF="YES", SPARSE_OK="TRUE") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2020:01:05 10:00:00")
    assert p.stat().st_size < 50_000_000
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "huge.tif", "200,000 x 200,000 px")


@pytest.mark.parametrize("make, words", [
    (lambda p: p.mkdir(), "not a file"),
    (lambda p: p.write_text(json.dumps({"acquired": "9999-12-31T00:00:00Z"})), "not a plausible date"),
    (lambda p: p.write_text(json.dumps({"acquired": "0001-01-01T00:00:00Z"})), "not a plausible date"),
])
def test_bad_time_sidecars(make, words, small_site, tmp_path, capsys):
    make(small_site / "images" / "a.json")
    for argv in (["run", str(small_site), "--out", str(tmp_path / "o"), "--quiet"], ["info", str(small_site)]):
        assert main(argv) == 2
        _one_line(capsys, "a.json", words)


def test_a_dsm_grid_that_cannot_fit_is_refused(small_site, tmp_path, capsys):
    (small_site / "site.json").write_text(json.dumps({"crs_epsg": 32632, "resolution_m": 0.01,
                                                      "bounds": [500000, 4980000, 501000, 4981000]}))
    assert main(["info", str(small_site)]) == 2
    _one_line(capsys, "site.json", "would not fit")
    (small_site / "site.json").write_text(json.dumps({"resolution_m": 0.001}))
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "site.json", "resolution_m must be")


@pytest.mark.parametrize("key, words", [("resolution", "did you mean 'resolution_m'"),
                                        ("crs", "did you mean 'crs_epsg'"), ("colour", "unknown key")])
def test_site_json_with_a_misspelt_key(key, words, small_site, tmp_path, capsys):
    (small_site / "site.json").write_text(json.dumps({key: 1}))
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "site.json", words)


def test_duplicate_gcp_ids_among_many(tmp_path):
    from recon_core.errors import InputError
    from recon_core.io.gcps import read_gcps_geojson
    from tests.conftest import gcp_feature

    feats = [gcp_feature(f"G{k}", 10 + 1e-6 * k, 45.0, 100.0, {}) for k in range(20_000)]
    feats.append(gcp_feature("G17", 10.0, 45.0, 100.0, {}))
    p = tmp_path / "g.geojson"
    p.write_text(json.dumps({"type": "FeatureCollection", "features": feats}))
    with pytest.raises(InputError, match=r"duplicate GCP ids \['G17'\]"):
        read_gcps_geojson(p)


def test_a_sidecar_added_after_sparse_makes_it_stale(tiny_site, tmp_path):
    from recon_core.config import preset
    from recon_core.io.site import load_site
    from recon_core.resume import stage_done

    site = tmp_path / "site"
    shutil.copytree(tiny_site, site)
    out = tmp_path / "out"
    cfg = preset("tiny")
    from recon_core.pipeline import run

    run(site, out, cfg, until="sparse")
    assert stage_done(out, "sparse", cfg, load_site(site))
    name = sorted((site / "images").glob("*.tif"))[0].stem
    (site / "images" / f"{name}.json").write_text(json.dumps({"acquired": "2019-01-01T10:00:00Z"}))
    assert not stage_done(out, "sparse", cfg, load_site(site))


# -- cases a hostile tester found (2026-11-27) ---------------------------------------------------
@pytest.mark.parametrize("write", [
    lambda s: (s / "c.toml").write_text("seed = 1" + "0" * 400 + "\n"),
    lambda s: (s / "site.json").write_text('{"resolution_m": 1' + "0" * 400 + "}"),
    lambda s: (s / "site.json").write_text('{"crs_epsg": NaN}'),
    lambda s: (s / "images" / "a.json").write_text('{"acquired": "9999-12-31T23:59:59-01:00"}'),
    lambda s: (s / "images" / "a.json").write_text('{"acquired": "2020-01-01T00:00:00Z", '
                                                    '"acquired": "2021-01-01T00:00:00Z"}'),
], ids=["huge-seed", "huge-resolution", "nan-epsg", "far-future-with-zone", "duplicate-key"])
def test_numbers_and_times_no_float_holds(write, small_site, tmp_path, capsys):
    write(small_site)
    extra = ["--config", str(small_site / "c.toml")] if (small_site / "c.toml").exists() else []
    assert _run(small_site, tmp_path, *extra) == 2
    _one_line(capsys)


def _gcp_file(site, coords_list, crs=None):
    from tests.conftest import gcp_feature

    feats = [gcp_feature(f"G{k}", *c, {"a.tif": [3.0, 4.0], "b.tif": [5.0, 6.0]}) for k, c in enumerate(coords_list)]
    doc = {"type": "FeatureCollection", "features": feats}
    if crs:
        doc["crs_epsg"] = crs
    (site / "gcps.geojson").write_text(json.dumps(doc))


def test_gcps_that_are_not_on_earth_or_far_from_the_others(small_site, tmp_path, capsys):
    _gcp_file(small_site, [(10.0, 45.0, 1e300)])
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "not on the Earth's surface")
    _gcp_file(small_site, [(500000.0, 4980000.0, 100.0), (1e30, 1e30, 100.0)], crs=32632)
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "G1")
    _gcp_file(small_site, [(10.0, 45.0, 100.0), (10.001, 45.0, 100.0), (10.0, 45.001, 120.0),
                           (20.0, 45.0, 100.0)])
    assert _run(small_site, tmp_path) == 2
    _one_line(capsys, "G3", "km from the others")


def test_a_site_of_one_image_per_date(small_site, tmp_path, capsys):
    with rasterio.open(small_site / "images" / "b.tif", "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2020:06:03 10:00:00")
    assert _run(small_site, tmp_path, "--stage", "sparse") == 2
    _one_line(capsys, "every date group has one image")


def test_pixels_rewritten_with_the_time_put_back_are_other_inputs(tiny_site, tmp_path):
    from recon_core.config import preset
    from recon_core.io.site import load_site
    from recon_core.pipeline import run
    from recon_core.resume import stage_done

    site = tmp_path / "site"
    shutil.copytree(tiny_site, site)
    out = tmp_path / "out"
    cfg = preset("tiny")
    img = sorted((site / "images").glob("*.tif"))[0]
    with rasterio.open(img) as src:          # uncompressed: a rewrite in place keeps the size
        prof, a, tags = src.profile, src.read(), src.tags()
    prof.update(compress=None, tiled=False)
    with rasterio.open(img, "w", **prof) as dst:
        dst.write(a)
        dst.update_tags(**tags)
    run(site, out, cfg, until="sparse")
    st = img.stat()
    with rasterio.open(img, "r+") as ds:
        a = ds.read(1)
        ds.write(np.roll(a, 6, axis=1), 1)
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert img.stat().st_size == st.st_size and img.stat().st_mtime_ns == st.st_mtime_ns
    assert not stage_done(out, "sparse", cfg, load_site(site))
    # one pixel, away from every window a sample would read, edited with the time put back
    run(site, out, cfg, until="sparse")
    st = img.stat()
    with rasterio.open(img, "r+") as ds:
        a = ds.read(1)
        a[a.shape[0] // 3 + 1, a.shape[1] // 3 + 1] ^= 1
        ds.write(a, 1)
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert not stage_done(out, "sparse", cfg, load_site(site))


def test_other_writers_into_a_run_folder(tiny_site, small_site, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", str(tiny_site), "--out", str(out), "--stage", "sparse", "--quiet", "--preset", "tiny"]) == 0
    capsys.readouterr()
    gt = small_site / "gt_dsm.tif"
    write_tiff(gt, np.ones((8, 8), np.float32))
    assert main(["eval", str(gt), str(gt), "--out", str(out / "eval")]) == 2
    _one_line(capsys, "inside the output folder")
    assert main(["gcps", "convert", str(tiny_site / "gcps.geojson"), str(tmp_path / "g.csv"),
                 "--epsg", "4269"]) == 2
    _one_line(capsys, "not a projected CRS")


def test_the_viewer_is_refused_on_a_folder_another_job_holds(tiny_site, tmp_path, capsys):
    import subprocess
    import sys
    import textwrap

    out = tmp_path / "out"
    out.mkdir()
    code = textwrap.dedent("""
        import sys, time
        from recon_core.io.lock import out_lock
        with out_lock(sys.argv[1]):
            print("held", flush=True)
            time.sleep(30)
    """)
    p = subprocess.Popen([sys.executable, "-c", code, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "held"
        assert main(["view", str(tiny_site), "--out", str(out), "--port", "0", "--no-browser-hint"]) == 2
        _one_line(capsys, f"PID {p.pid}")
        assert not (out / "gcps.geojson").exists()
    finally:
        p.kill()
        p.wait()


def test_a_partial_run_after_the_gcps_changed_drops_the_stale_products(tiny_run, tmp_path):
    from recon_core.config import preset
    from recon_core.io.layout import OutLayout
    from recon_core.pipeline import run

    state, _ = tiny_run
    site, out = tmp_path / "site", tmp_path / "out"
    shutil.copytree(state.site.root, site)
    shutil.copytree(state.out, out)
    doc = json.loads((site / "gcps.geojson").read_text())
    doc["features"] = doc["features"][:-1]
    (site / "gcps.geojson").write_text(json.dumps(doc))
    run(site, out, preset("tiny"), until="dense")
    lay = OutLayout(out)
    assert not lay.dsm.exists() and not lay.stage_record("upgrade").exists()
    assert lay.dense_ply(0).exists()


def test_gcps_with_lon_and_lat_swapped_are_refused_by_the_images_footprints(tiny_site, tmp_path, capsys):
    """No site.json, GCPs with lon and lat swapped: the images' RPCs (read for this check only)
    put the site elsewhere; run refuses before any compute naming the GCP file and the fault,
    info warns."""
    import shutil

    site = tmp_path / "site"
    shutil.copytree(tiny_site, site)
    (site / "site.json").unlink()
    doc = json.loads((site / "gcps.geojson").read_text())
    for f in doc["features"]:
        c = f["geometry"]["coordinates"]
        c[0], c[1] = c[1], c[0]
    (site / "gcps.geojson").write_text(json.dumps(doc))
    assert main(["run", str(site), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "gcps.geojson" in err[0] and "lon and lat are swapped" in err[0], err
    assert not (tmp_path / "o" / "stages").exists()
    assert main(["info", str(site)]) == 0
    assert "would refuse" in capsys.readouterr().out


def test_a_run_that_cannot_fit_in_memory_is_refused_before_any_compute(small_site, tmp_path, capsys, monkeypatch):
    """The pre-flight estimates each stage's memory (recon_core.memory): a machine without
    enough for one of them refuses the run before any compute, naming the stage, what drives
    it and what to change; a larger ground truth raises the evaluation's figure."""
    import recon_core.memory as memory
    from recon_core.config import Config
    from recon_core.io.site import load_site

    write_tiff(small_site / "gt_dsm.tif", np.zeros((64, 64), np.float32))
    small = {e.stage: e.mb for e in memory.estimate(load_site(small_site), Config())}
    assert set(small) == {"sparse", "dense", "dsm", "eval"} and all(v > 0 for v in small.values())
    write_tiff(small_site / "gt_dsm.tif", np.zeros((4000, 4000), np.float32))
    big = {e.stage: e.mb for e in memory.estimate(load_site(small_site), Config())}
    assert big["eval"] - small["eval"] == pytest.approx(memory.EVAL_GT_BYTES * (4000 ** 2 - 64 ** 2) / 2 ** 20)
    monkeypatch.setattr(memory, "available_mb", lambda: 10.0)
    assert main(["run", str(small_site), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "stage would need about" in err[0] and "0.0 GB available" in err[0], err
    assert not (tmp_path / "o" / "stages").exists()
