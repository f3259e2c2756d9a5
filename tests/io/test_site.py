"""Site reading: good input reads back; every kind of bad input is one clear InputError."""

from __future__ import annotations

import json
from datetime import datetime, timezone

import numpy as np
import pytest

from recon_core.cli import main
from recon_core.errors import InputError
from recon_core.io.gcps import GCP, read_gcps_geojson, write_gcps_geojson
from recon_core.io.site import load_site, read_window
from tests.conftest import gcp_feature, write_tiff


def test_reads_small_site(small_site):
    site = load_site(small_site)
    assert [im.name for im in site.images] == ["a.tif", "b.tif"]
    assert site.images[0].width == 64 and site.images[0].height == 48
    assert site.images[1].acquired == datetime(2020, 1, 3, 10, tzinfo=timezone.utc)
    assert site.gcps[0].observations["b.tif"] == (5.5, 6.5)
    w = read_window(site.images[0], 10, 5, 20, 7)
    assert w.shape == (7, 20) and w.dtype == np.float32


def test_sidecar_time_wins(small_site):
    (small_site / "images" / "a.json").write_text(json.dumps({"acquired": "2021-05-06T07:08:09Z"}))
    site = load_site(small_site)
    assert site.image("a.tif").acquired == datetime(2021, 5, 6, 7, 8, 9, tzinfo=timezone.utc)
    assert site.image("a.tif").time_source == "sidecar"


def test_a_sidecar_may_state_the_view_alone(small_site):
    """`view` (the vendor's viewing direction) in a sidecar without `acquired`: the time stays
    the TIFF's, the view is read (azimuth modulo 360)."""
    (small_site / "images" / "a.json").write_text(json.dumps({"view": {"incidence_deg": 17.2, "azimuth_deg": -145.5}}))
    (small_site / "images" / "b.json").write_text(json.dumps({"acquired": "2020-01-03T10:00:00Z",
                                                               "view": {"incidence_deg": 5, "azimuth_deg": 10}}))
    site = load_site(small_site)
    a, b = site.image("a.tif"), site.image("b.tif")
    assert a.time_source == "TIFFTAG_DATETIME" and a.acquired == datetime(2020, 1, 2, 10, tzinfo=timezone.utc)
    assert (a.view.incidence_deg, a.view.azimuth_deg) == (17.2, 214.5)
    assert b.time_source == "sidecar" and b.view.incidence_deg == 5.0
    assert a.to_dict()["view"] == {"incidence_deg": 17.2, "azimuth_deg": 214.5}


@pytest.mark.parametrize("view, words", [
    ({"incidence_deg": 95.0, "azimuth_deg": 10.0}, "not an angle from the vertical"),
    ({"incidence_deg": "17", "azimuth_deg": 10.0}, "incidence_deg is \"17\""),
    ({"incidence_deg": 17.0}, "\"view\" must be"),
    ({"incidence_deg": 17.0, "azimuth_deg": 10.0, "elevation_deg": 73.0}, "\"view\" must be"),
    ({"incidence_deg": 17.0, "azimuth_deg": float("nan")}, "azimuth_deg is NaN"),
    ([17.0, 10.0], "\"view\" must be"),
])
def test_a_wrong_view_is_refused_naming_the_sidecar(small_site, view, words):
    (small_site / "images" / "a.json").write_text(json.dumps({"view": view}))
    err = _expect_error(small_site, words)
    assert err.path.endswith("a.json")


def test_gcps_round_trip(tmp_path, small_site):
    site = load_site(small_site)
    site.gcps.append(GCP("G2", 10.001, 45.002, 120.5, "check", 0.1, {"a.tif": (1.0, 2.0)}, sigma_h_m=3.5))
    write_gcps_geojson(tmp_path / "g.geojson", site.gcps)
    back = read_gcps_geojson(tmp_path / "g.geojson")
    assert [g.id for g in back] == ["G1", "G2"]
    assert back[1].role == "check" and back[1].sigma_m == 0.1 and back[1].sigma_h_m == 3.5
    assert back[0].sigma_h_m is None
    assert back[1].lat == pytest.approx(45.002, abs=1e-9)


def test_projected_gcp_crs(tmp_path):
    fc = {"type": "FeatureCollection", "crs_epsg": 32633,
          "features": [gcp_feature("P", 500000.0, 4983000.0, 50.0, {})]}
    (tmp_path / "g.geojson").write_text(json.dumps(fc))
    g = read_gcps_geojson(tmp_path / "g.geojson")[0]
    assert g.lon == pytest.approx(15.0, abs=1e-6) and 44.9 < g.lat < 45.1 and g.h == 50.0


def _expect_error(site, fragment):
    with pytest.raises(InputError) as ei:
        load_site(site)
    assert fragment in str(ei.value)
    return ei.value


def test_no_images(tmp_path):
    (tmp_path / "images").mkdir()
    err = _expect_error(tmp_path, "no .tif")
    assert err.path.endswith("images")


def test_no_images_folder(tmp_path):
    _expect_error(tmp_path, "no images/ folder")


def test_not_a_geotiff(small_site):
    (small_site / "images" / "c.tif").write_bytes(b"this is not a tiff at all" * 10)
    err = _expect_error(small_site, "not a GeoTIFF")
    assert err.path.endswith("c.tif")


def test_png_named_tif(small_site):
    import cv2

    cv2.imwrite(str(small_site / "images" / "p.png"), np.zeros((8, 8), np.uint8))
    (small_site / "images" / "p.png").rename(small_site / "images" / "p.tif")
    err = _expect_error(small_site, "GDAL reads it as PNG")
    assert err.path.endswith("p.tif")


def _move_out(small_site, name):
    """Move images/NAME out of the site (to wrap or convert it) and give it a sidecar time."""
    src = small_site / "images" / name
    dst = small_site.parent / name
    src.rename(dst)
    (small_site / "images" / (src.stem + ".json")).write_text(json.dumps({"acquired": "2020-01-02T10:00:00Z"}))
    return dst


def test_vrt_and_jpeg2000_images_read_like_their_geotiff(small_site):
    """Products delivered as a VRT (mosaic of tiles) or JPEG 2000 are images of the site; the
    pixels read are those of the source (lossless JPEG 2000)."""
    import rasterio
    from rasterio.shutil import copy as gdal_copy

    ref = [read_window(im, 0, 0, 64, 48) for im in load_site(small_site).images]
    a = _move_out(small_site, "a.tif")
    gdal_copy(a, small_site / "images" / "a.vrt", driver="VRT")
    b = _move_out(small_site, "b.tif")
    gdal_copy(b, small_site / "images" / "b.jp2", driver="JP2OpenJPEG", REVERSIBLE="YES", QUALITY="100")
    site = load_site(small_site, read_gcps=False)     # its GCPs name a.tif and b.tif
    assert [im.name for im in site.images] == ["a.vrt", "b.jp2"]
    for old, new in zip(ref, site.images):
        np.testing.assert_array_equal(old, read_window(new, 0, 0, 64, 48))
    with rasterio.open(small_site / "images" / "b.jp2") as ds:
        assert ds.driver == "JP2OpenJPEG"


def test_a_vrt_wrapping_a_sibling_is_refused(small_site):
    from rasterio.shutil import copy as gdal_copy

    gdal_copy(small_site / "images" / "a.tif", small_site / "images" / "a2.vrt", driver="VRT")
    err = _expect_error(small_site, "wraps a.tif, which is also in images/")
    assert err.path.endswith("a2.vrt")


def test_two_images_of_one_name_are_refused(small_site):
    from rasterio.shutil import copy as gdal_copy

    gdal_copy(small_site / "images" / "a.tif", small_site / "images" / "a.jp2", driver="JP2OpenJPEG")
    err = _expect_error(small_site, "has the name of")
    assert err.path.endswith(".tif") or err.path.endswith(".jp2")


def test_truncated_tiff(small_site):
    big = small_site / "images" / "big.tif"
    write_tiff(big, np.random.default_rng(1).integers(0, 2047, (400, 300), dtype=np.uint16))
    data = big.read_bytes()
    big.write_bytes(data[: len(data) // 2])
    err = _expect_error(small_site, "truncated")
    assert err.path.endswith("big.tif")


def test_missing_time(small_site):
    write_tiff(small_site / "images" / "c.tif", np.arange(64, dtype=np.uint16).reshape(8, 8), when=None)
    err = _expect_error(small_site, "no acquisition time")
    assert err.path.endswith("c.tif")


def test_bad_sidecar(small_site):
    (small_site / "images" / "a.json").write_text("{not json")
    err = _expect_error(small_site, "sidecar")
    assert err.path.endswith("a.json")


def _write_gcps(site, features):
    (site / "gcps.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": features}))


def test_gcp_unknown_image(small_site):
    _write_gcps(small_site, [gcp_feature("G1", 10, 45, 1, {"zzz.tif": [1, 1]})])
    err = _expect_error(small_site, "unknown image 'zzz.tif'")
    assert err.path.endswith("gcps.geojson")


def test_gcp_observation_outside(small_site):
    _write_gcps(small_site, [gcp_feature("G1", 10, 45, 1, {"a.tif": [70.0, 3.0]})])
    _expect_error(small_site, "lies outside a.tif")


def test_malformed_geojson(small_site):
    (small_site / "gcps.geojson").write_text('{"type": "FeatureCollection", "features": [')
    _expect_error(small_site, "malformed GeoJSON")


def test_geojson_wrong_structure(small_site):
    (small_site / "gcps.geojson").write_text('{"type": "Feature"}')
    _expect_error(small_site, "FeatureCollection")


def test_gcp_bad_coordinates(small_site):
    _write_gcps(small_site, [gcp_feature("G1", 10, 45, 1, {})])
    doc = json.loads((small_site / "gcps.geojson").read_text())
    doc["features"][0]["geometry"]["coordinates"] = [10, 45]
    (small_site / "gcps.geojson").write_text(json.dumps(doc))
    _expect_error(small_site, "coordinates must be")


def test_bad_site_json(small_site):
    (small_site / "site.json").write_text(json.dumps({"bounds": [5, 5, 1, 1]}))
    _expect_error(small_site, "bounds")


def test_cli_error_is_one_line(small_site, capsys):
    (small_site / "images" / "c.tif").write_bytes(b"garbage" * 20)
    code = main(["info", str(small_site)])
    err = capsys.readouterr().err
    assert code != 0
    assert err.strip().count("\n") == 0 and "c.tif" in err and "Traceback" not in err


def test_cli_info_real_data(shared_data, capsys):
    assert main(["info", str(shared_data / "reunion_pair")]) == 0
    out = capsys.readouterr().out
    assert "2 image(s)" in out and "1 date group(s)" in out and "4 control, 8 check" in out


def test_hidden_files_in_images_are_not_images(small_site):
    """An interrupted atomic write leaves `.img.tif.XXXX.tif`; macOS leaves `._a.tif`: neither is
    an image of the site (one such file once entered a benchmark as a blank fourth view)."""
    import shutil

    from recon_core.io.site import load_site

    shutil.copy(small_site / "images" / "a.tif", small_site / "images" / ".a.tif.x1y2.tif")
    shutil.copy(small_site / "images" / "a.tif", small_site / "images" / "._a.tif")
    assert [im.name for im in load_site(small_site).images] == ["a.tif", "b.tif"]


def test_a_vrts_content_hash_follows_its_sources(tmp_path):
    """The fingerprint of a VRT image (what `aerec site init` writes) changes when a source it
    reads is edited, even though the VRT file itself is unchanged (its own hash is cached)."""
    from recon_core.io.fingerprint import content_hash

    src = write_tiff(tmp_path / "src.tif", np.arange(48 * 64, dtype=np.uint16).reshape(48, 64))
    vrt = tmp_path / "v.vrt"
    vrt.write_text(f'<VRTDataset rasterXSize="64" rasterYSize="48"><VRTRasterBand dataType="UInt16" band="1">'
                   f'<SimpleSource><SourceFilename relativeToVRT="0">{src}</SourceFilename><SourceBand>1</SourceBand>'
                   f'</SimpleSource></VRTRasterBand></VRTDataset>')
    cache: dict = {}
    before = content_hash(vrt, cache)
    assert content_hash(vrt, cache) == before
    data = bytearray(src.read_bytes())
    data[-1] ^= 0xFF
    src.write_bytes(bytes(data))
    assert content_hash(vrt, cache) != before
