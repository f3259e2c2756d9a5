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
    from recon_core.pipeline import check_images
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
    from recon_core.pipeline import stage_done

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
