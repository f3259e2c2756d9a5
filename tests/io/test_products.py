"""`aerec site init`: a site from vendor products, no pixel copied, times from the products'
metadata as GDAL reads it (fixtures of each layout are written here, a few KB each)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import rasterio

from recon_core.cli import main

DIMAP = """<?xml version="1.0" encoding="UTF-8"?>
<Dimap_Document>
 <Dataset_Sources><Source_Identification><Strip_Source>
  <MISSION>PHR</MISSION><MISSION_INDEX>{index}</MISSION_INDEX>
  <IMAGING_DATE>{date}</IMAGING_DATE><IMAGING_TIME>{time}</IMAGING_TIME>
 </Strip_Source></Source_Identification></Dataset_Sources>
</Dimap_Document>
"""


def _write(path, arr, driver="GTiff", **kw):
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", driver=driver, width=arr.shape[-1], height=arr.shape[-2],
                       count=1 if arr.ndim == 2 else arr.shape[0], dtype=arr.dtype, **kw) as ds:
        ds.write(arr if arr.ndim == 3 else arr[None])
    return path


def _dimap(folder, stem, arr, date="2013-02-08", time="08:36:09.1Z", index="1A", tiles=1):
    """A Pleiades-like product: IMG_<stem>_R1C<k>.TIF tiles and DIM_<stem>.XML beside them."""
    w = arr.shape[1] // tiles
    for k in range(tiles):
        _write(folder / f"IMG_{stem}_R1C{k + 1}.TIF", np.ascontiguousarray(arr[:, k * w:(k + 1) * w]))
    (folder / f"DIM_{stem}.XML").write_text(DIMAP.format(date=date, time=time, index=index))


def test_dimap_products_with_tiles_become_vrts_with_their_times(tmp_path, capsys):
    rng = np.random.default_rng(0)
    a, b = (rng.integers(0, 2047, (64, 96)).astype(np.uint16) for _ in range(2))
    _dimap(tmp_path / "p1", "PHR1A_P_201302080836091_SEN_1", a, tiles=2)
    _dimap(tmp_path / "p2", "PHR1B_P_201302080836013_SEN_2", b, time="08:36:01.3Z", index="1B")
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(tmp_path / "p1"), str(tmp_path / "p2")]) == 0
    out = capsys.readouterr().out
    assert "PHR 1A" in out and "2 tiles" in out
    vrts = sorted((site / "images").glob("*.vrt"))
    assert [v.stem for v in vrts] == ["IMG_PHR1A_P_201302080836091_SEN_1", "IMG_PHR1B_P_201302080836013_SEN_2"]
    with rasterio.open(vrts[0]) as ds:                       # the two tiles, side by side
        np.testing.assert_array_equal(ds.read(1), a)
    side = json.loads(vrts[1].with_suffix(".json").read_text())
    assert side["acquired"] == "2013-02-08T08:36:01Z" and side["satellite"] == "PHR 1B"
    assert json.loads((site / "gcps.geojson").read_text())["features"] == []
    assert sum(p.stat().st_size for p in site.rglob("*")) < 20_000      # no pixel copied
    assert main(["info", str(site)]) == 0
    info = capsys.readouterr().out
    assert "sensor PHR 1A" in info and "1 date group" in info


DIMAP_ANGLES = """ <Geometric_Data><Use_Area>
  <Located_Geometric_Values><LOCATION_TYPE>Top Center</LOCATION_TYPE><Acquisition_Angles>
   <AZIMUTH_ANGLE>180.1</AZIMUTH_ANGLE><INCIDENCE_ANGLE>10.0</INCIDENCE_ANGLE>
   <INCIDENCE_ANGLE_ALONG_TRACK>4.0</INCIDENCE_ANGLE_ALONG_TRACK><INCIDENCE_ANGLE_ACROSS_TRACK>-9.0</INCIDENCE_ANGLE_ACROSS_TRACK>
  </Acquisition_Angles></Located_Geometric_Values>
  <Located_Geometric_Values><LOCATION_TYPE>Center</LOCATION_TYPE><Acquisition_Angles>
   <AZIMUTH_ANGLE>180.5</AZIMUTH_ANGLE><INCIDENCE_ANGLE>12.0</INCIDENCE_ANGLE>
   <INCIDENCE_ANGLE_ALONG_TRACK>0.0</INCIDENCE_ANGLE_ALONG_TRACK><INCIDENCE_ANGLE_ACROSS_TRACK>-12.0</INCIDENCE_ANGLE_ACROSS_TRACK>
  </Acquisition_Angles></Located_Geometric_Values>
 </Use_Area></Geometric_Data>
</Dimap_Document>
"""

MAXAR_IMD = """version = "AA";
BEGIN_GROUP = IMAGE_1
	satId = "WV03";
	firstLineTime = 2015-02-01T10:31:22.123456Z;
	meanSatEl = 70.5;
	meanSatAz = 215.3;
END_GROUP = IMAGE_1
END;
"""


def test_the_viewing_direction_comes_from_the_products_metadata_or_the_user(tmp_path, capsys):
    """DIMAP: the Center's incidence, the azimuth from the orientation and the along- and
    across-track incidences; Maxar: 90 - satEl and satAz; --view for a product without them."""
    rng = np.random.default_rng(1)
    _dimap(tmp_path / "p1", "PHR1A_P_1", rng.integers(0, 2047, (48, 64)).astype(np.uint16))
    dim = tmp_path / "p1" / "DIM_PHR1A_P_1.XML"
    dim.write_text(dim.read_text().replace("</Dimap_Document>\n", DIMAP_ANGLES))
    _write(tmp_path / "p2" / "15FEB01-P1BS-X.TIF", rng.integers(0, 2047, (48, 64)).astype(np.uint16))
    (tmp_path / "p2" / "15FEB01-P1BS-X.IMD").write_text(MAXAR_IMD)
    _write(tmp_path / "p3" / "plain.tif", rng.integers(0, 2047, (48, 64)).astype(np.uint16))
    site = tmp_path / "site"
    assert main(["site", "init", str(site), *(str(tmp_path / p) for p in ("p1", "p2", "p3")),
                 "--view", "plain=15.5,-20", "--time", "plain=2015-02-03T10:00:00Z"]) == 0
    side = {p.stem: json.loads(p.read_text()) for p in (site / "images").glob("*.json")}
    # across-track -12 (looking to the left of an image oriented 180.5 from north), along 0
    assert side["IMG_PHR1A_P_1"]["view"] == {"incidence_deg": 12.0, "azimuth_deg": pytest.approx(270.5)}
    assert side["15FEB01-P1BS-X"]["view"] == {"incidence_deg": pytest.approx(19.5), "azimuth_deg": 215.3}
    assert side["plain"]["view"] == {"incidence_deg": 15.5, "azimuth_deg": 340.0}
    assert side["plain"]["view_source"] == "--view"
    from recon_core.io.site import load_site
    assert all(im.view is not None for im in load_site(site).images)
    assert main(["site", "init", str(tmp_path / "s2"), str(tmp_path / "p3"), "--view", "plain=95,10",
                 "--time", "plain=2015-02-03T10:00:00Z"]) == 2
    assert "--view 'plain=95,10'" in capsys.readouterr().err


def test_nitf_geotiff_and_a_given_time(tmp_path, capsys):
    rng = np.random.default_rng(1)
    _write(tmp_path / "wv" / "17MAY.NTF", rng.integers(0, 2047, (64, 64)).astype(np.uint16), driver="NITF",
           IDATIM="20170503104217")
    g = _write(tmp_path / "g" / "scene.tif", rng.integers(0, 255, (64, 64)).astype(np.uint8))
    with rasterio.open(g, "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2017:05:03 10:43:01")
    _write(tmp_path / "none" / "bare.tif", rng.integers(0, 255, (64, 64)).astype(np.uint8))
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(tmp_path / "wv"), str(g), str(tmp_path / "none" / "bare.tif"),
                 "--time", "bare=2017-05-03T10:44:00Z"]) == 0
    times = {p.stem: json.loads(p.read_text())["acquired"] for p in (site / "images").glob("*.json")}
    assert times == {"17MAY": "2017-05-03T10:42:17Z", "scene": "2017-05-03T10:43:01Z",
                     "bare": "2017-05-03T10:44:00Z"}


def test_a_full_scene_footprint_gets_a_dsm_resolution_that_fits(tmp_path, capsys):
    """A 20 km footprint of a 0.5 m GSD scene at the default 0.5 m is 1.6e9 DSM cells, more than a
    site.json may ask for: site init names a coarser resolution_m (and says so), and `aerec info`
    reads the site."""
    from rasterio.transform import from_origin

    g = tmp_path / "g" / "scene.tif"        # 20 km at 0.5 m, sparse: no pixel written
    g.parent.mkdir()
    with rasterio.open(g, "w", driver="GTiff", width=40_000, height=40_000, count=1, dtype="uint8",
                       crs="EPSG:32740", transform=from_origin(330000.0, 7660000.0, 0.5, 0.5),
                       tiled=True, sparse_ok=True) as ds:
        ds.write(np.random.default_rng(2).integers(0, 255, (1, 64, 64)).astype(np.uint8),
                 window=rasterio.windows.Window(0, 0, 64, 64))
    with rasterio.open(g, "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2024:03:02 10:41:31")
    g2 = g.with_name("scene2.tif")                 # the pair's other view, a minute later
    shutil.copy(g, g2)
    with rasterio.open(g2, "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME="2024:03:02 10:42:31")
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(g), str(g2)]) == 0
    assert "resolution_m is 1 m" in capsys.readouterr().out
    hints = json.loads((site / "site.json").read_text())
    assert hints["resolution_m"] == 1.0 and hints["bounds"] == [330000.0, 7640000.0, 350000.0, 7660000.0]
    assert main(["info", str(site)]) == 0


@pytest.mark.parametrize("make, words", [
    (lambda d: _write(d / "bare.tif", np.ones((64, 64), np.uint8)), "no acquisition time in its metadata"),
    (lambda d: _dimap(d, "PHR1A_X", np.ones((64, 64), np.uint16), date="2013-13-45"), "IMAGING_DATE"),
    (lambda d: _write(d / "ms.tif", np.ones((4, 64, 64), np.uint16)), "choose the panchromatic one with --band"),
], ids=["no-time", "bad-date", "four-bands"])
def test_bad_metadata_is_one_line_and_nothing_is_written(make, words, tmp_path, capsys):
    make(tmp_path / "p")
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err
    assert not site.exists()


def test_a_pleiades_like_site_from_the_real_crops_reconstructs(shared_data, tmp_path, capsys):
    """The real Gizeh crops' pixels as DIMAP-like products; the site `site init` writes runs to
    the dense stage (the GCPs' observations name the original files)."""
    src = shared_data / "gizeh_pair" / "images"
    for k, (name, t) in enumerate((("img1", "08:36:09.1Z"), ("img2", "08:36:01.3Z"))):
        with rasterio.open(src / f"{name}.tif") as ds:
            a = ds.read(1)
        _dimap(tmp_path / f"prod{k}", f"PHR1A_P_20130208_SEN_{k}", a, time=t)
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(tmp_path / "prod0"), str(tmp_path / "prod1")]) == 0
    assert main(["run", str(site), "--out", str(tmp_path / "out"), "--stage", "dense", "--tile-size", "400",
                 "--quiet"]) == 0
    rep = json.loads((tmp_path / "out" / "report.json").read_text())
    g = rep["stages"]["sparse"]["groups"]["0"]
    assert g["tiles_registered"] == g["tiles_total"] and rep["stages"]["dense"]["groups"]["0"]["points"] > 10_000
    shutil.rmtree(tmp_path / "out")


def test_a_footprint_that_fits_at_the_gsd_leaves_the_resolution_to_the_run():
    """The same 20 km footprint: a 40,000 px scene (GSD 0.5 m) cannot be gridded at 0.5 m, so
    site.json names 1 m; a 6,000 px scene (GSD 3.3 m) fits at its own GSD-based cell (3.5 m), so
    site.json names none and the run's default stands (it used to be pinned at 1 m, finer than
    the images can see)."""
    from datetime import datetime, timezone

    from recon_core.io.products import ProductImage, site_grid

    corners = [(330000.0, 7660000.0), (350000.0, 7660000.0), (350000.0, 7640000.0), (330000.0, 7640000.0)]

    def scene(px):
        return ProductImage(name="s", files=[], acquired=datetime(2024, 3, 2, tzinfo=timezone.utc),
                            time_source="t", satellite=None, band=1, width=px, height=px, dtype="uint16",
                            crs_footprint=("EPSG:32740", corners))

    fine, note = site_grid([scene(40_000)])
    assert fine["resolution_m"] == 1.0 and "resolution_m is 1 m" in note and "from the GSD" in note
    coarse, note = site_grid([scene(6_000)])
    assert "resolution_m" not in coarse and coarse["bounds"] == [330000.0, 7640000.0, 350000.0, 7660000.0]


def _tiles(folder, stem, arrays: dict):
    """IMG_<stem>_R<r>C<c>.TIF tiles from {(r, c): array} and a DIMAP beside them."""
    for (r, c), a in arrays.items():
        _write(folder / f"IMG_{stem}_R{r}C{c}.TIF", a)
    (folder / f"DIM_{stem}.XML").write_text(DIMAP.format(date="2013-02-08", time="08:36:09.1Z", index="1A"))


@pytest.mark.parametrize("layout, words", [
    ({(1, 1): (32, 40), (1, 3): (32, 40)}, "R1C2 .. missing"),               # a tile gone
    ({(1, 1): (32, 40), (1, 2): (30, 40)}, "do not fit together"),           # a short tile
    ({(1, 1): (32, 40), (2, 2): (32, 40), (2, 1): (32, 40)}, "R1C2"),        # a grid with a hole
])
def test_a_tiled_product_with_a_missing_or_mis_sized_tile_is_refused(layout, words, tmp_path, capsys):
    rng = np.random.default_rng(2)
    _tiles(tmp_path / "p", "PHR1A_P_9", {k: rng.integers(0, 2047, v).astype(np.uint16) for k, v in layout.items()})
    site = tmp_path / "site"
    assert main(["site", "init", str(site), str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "PHR1A_P_9" in err[0], err
    for w in words.split(" .. "):
        assert w in err[0], err
    assert not site.exists() and not list(tmp_path.glob(".site.partial-*"))


def test_a_product_whose_tiles_do_not_make_its_declared_size_is_refused(tmp_path, capsys):
    rng = np.random.default_rng(3)
    _tiles(tmp_path / "p", "PHR1A_P_8", {(1, 1): rng.integers(0, 2047, (32, 40)).astype(np.uint16)})
    dim = tmp_path / "p" / "DIM_PHR1A_P_8.XML"
    dim.write_text(dim.read_text().replace("</Dimap_Document>", "<Raster_Data><Raster_Dimensions><NROWS>32</NROWS>"
                                           "<NCOLS>80</NCOLS></Raster_Dimensions></Raster_Data></Dimap_Document>"))
    assert main(["site", "init", str(tmp_path / "site"), str(tmp_path / "p")]) == 2
    assert "declares 80 x 32" in capsys.readouterr().err


def _product(path, arr, when="2015:02:03 10:00:00", origin=None):
    from rasterio.transform import from_origin

    kw = {} if origin is None else {"crs": "EPSG:32631", "transform": from_origin(*origin, 0.5, 0.5)}
    _write(path, arr, **kw)
    with rasterio.open(path, "r+") as ds:
        ds.update_tags(TIFFTAG_DATETIME=when)
    return path


def test_site_init_refuses_what_info_and_run_would_and_writes_nothing(tmp_path, capsys):
    """Every refusal is one line, exit 2, and no site (nor a hidden partial one) is left: a pixel
    type a site cannot hold, a GCP file naming an image of no product, products 1,000 km apart,
    a site inside the product folder; the corrected command then succeeds."""
    rng = np.random.default_rng(4)
    a = _product(tmp_path / "p" / "a.tif", rng.integers(0, 2047, (40, 48)).astype(np.uint16), origin=(500000, 4500000))
    b = _product(tmp_path / "p" / "b.tif", rng.integers(0, 2047, (40, 48)).astype(np.uint16),
                 "2015:02:04 10:00:00", origin=(500100, 4500050))
    far = _product(tmp_path / "far" / "c.tif", rng.integers(0, 2047, (40, 48)).astype(np.uint16),
                   origin=(500000, 5500000))
    i16 = _product(tmp_path / "i16" / "d.tif", rng.integers(0, 2047, (40, 48)).astype(np.int16))
    gcps = tmp_path / "g.geojson"
    gcps.write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "Point", "coordinates": [3.0, 40.6, 50.0]},
         "properties": {"id": "G1", "observations": {"a.vrt": [3, 4], "other.tif": [5, 6]}}}]}))
    site = tmp_path / "site"
    for argv, words in (([str(a), str(b), str(i16)], "pixel type int16"),
                        ([str(a), str(b), "--gcps", str(gcps)], "unknown image 'other.tif'"),
                        ([str(a), str(b), str(far)], "km from the other products"),
                        ([str(tmp_path / "p")], "inside the product folder")):
        target = tmp_path / "p" / "site" if words.startswith("inside") else site
        assert main(["site", "init", str(target), *argv]) == 2, words
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], err
        assert not site.exists() and not (tmp_path / "p" / "site").exists()
        assert not list(tmp_path.glob(".*partial*")) and not list((tmp_path / "p").glob(".*partial*"))
    assert main(["site", "init", str(site), str(a), str(b)]) == 0
    assert main(["info", str(site)]) == 0


def test_a_vrt_product_with_a_missing_source_is_refused_naming_it(tmp_path, capsys):
    rng = np.random.default_rng(5)
    src = _product(tmp_path / "src" / "s.tif", rng.integers(0, 2047, (40, 48)).astype(np.uint16))
    vrt = tmp_path / "p" / "v.vrt"
    vrt.parent.mkdir()
    vrt.write_text(f'<VRTDataset rasterXSize="48" rasterYSize="40"><Metadata><MDI key="TIFFTAG_DATETIME">'
                   f'2015:02:03 10:00:00</MDI></Metadata><VRTRasterBand dataType="UInt16" band="1"><SimpleSource>'
                   f'<SourceFilename relativeToVRT="0">{src}</SourceFilename><SourceBand>1</SourceBand>'
                   f'</SimpleSource></VRTRasterBand></VRTDataset>')
    src.unlink()
    assert main(["site", "init", str(tmp_path / "site"), str(vrt), "--time", "v=2015-02-03T10:00:00Z"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "v.vrt" in err[0], err
    assert not (tmp_path / "site").exists()


def test_two_files_for_one_tile_or_one_product_twice_are_refused(tmp_path, capsys):
    """R1C1 and R01C01 are one tile: refused naming both (the mosaic would take one of them
    silently); a product given twice is one image, and a site of one image is refused as `aerec
    run` would refuse it."""
    rng = np.random.default_rng(6)
    _tiles(tmp_path / "p", "PHR1A_P_7", {(1, 1): rng.integers(0, 2047, (32, 40)).astype(np.uint16),
                                         (1, 2): rng.integers(0, 2047, (32, 40)).astype(np.uint16)})
    _write(tmp_path / "p" / "IMG_PHR1A_P_7_R01C01.TIF", rng.integers(0, 2047, (32, 40)).astype(np.uint16))
    assert main(["site", "init", str(tmp_path / "site"), str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "R1C1" in err[0] and "two files for one tile" in err[0], err
    a = _product(tmp_path / "q" / "a.tif", rng.integers(0, 2047, (40, 48)).astype(np.uint16), origin=(500000, 4500000))
    assert main(["site", "init", str(tmp_path / "site"), str(a), str(a)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "one image" in err[0], err
    assert not (tmp_path / "site").exists()
