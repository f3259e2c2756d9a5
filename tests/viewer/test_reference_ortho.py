"""GCP ground positions picked on a reference orthoimage + DEM (no survey): a click on the
orthoimage in the viewer gives a new GCP, or the selected one, its lon/lat (the orthoimage's
georeferencing) and its height (the DEM's, bilinear); the GCPs' ground positions are marked on
it; bad references are refused in one line before the viewer starts."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import rasterio
from pyproj import Transformer

from aerec_viewer.cli import main as view_main
from aerec_viewer.gcp_session import GcpError
from recon_core.errors import InputError
from recon_core.euclidean.ground_reference import open_ground_reference


def _reference(tmp_path, site):
    """An orthoimage (random texture) on the ground-truth DSM's grid, that DSM as the DEM."""
    with rasterio.open(site / "gt_dsm.tif") as src:
        dem = src.read(1)
        crs, tf = src.crs, src.transform
    h, w = dem.shape
    ortho = tmp_path / "ortho.tif"
    rng = np.random.default_rng(0)
    with rasterio.open(ortho, "w", driver="GTiff", width=w, height=h, count=1, dtype="uint8",
                       crs=crs, transform=tf) as dst:
        dst.write(rng.integers(0, 255, (1, h, w)).astype(np.uint8))
    dem_path = tmp_path / "dem.tif"
    shutil.copy(site / "gt_dsm.tif", dem_path)
    return ortho, dem_path, dem, crs, tf


def test_the_ground_at_an_orthoimage_pixel(tiny_site, tmp_path):
    ortho, dem_path, dem, crs, tf = _reference(tmp_path, tiny_site)
    ref = open_ground_reference(ortho, dem_path)
    col, row = 37, 52                           # a cell centre: bilinear is the cell's own value
    lon, lat, h = ref.ground_at(col, row)
    e, n = tf.c + (col + 0.5) * tf.a, tf.f + (row + 0.5) * tf.e
    lon0, lat0 = Transformer.from_crs(crs, "EPSG:4326", always_xy=True).transform(e, n)
    assert (lon, lat) == pytest.approx((lon0, lat0), abs=1e-9)
    assert h == pytest.approx(float(dem[row, col]), abs=1e-4)
    c, r = ref.pixel_of([lon], [lat])
    assert (c[0], r[0]) == pytest.approx((col, row), abs=1e-6)
    # halfway between two cells: the mean of the two
    assert ref.ground_at(col + 0.5, row)[2] == pytest.approx(float(dem[row, col:col + 2].mean()), abs=1e-3)
    assert open_ground_reference(ortho).ground_at(col, row)[2] is None        # no DEM: no height


def test_bad_references_are_refused_in_one_line(tiny_site, tmp_path, capsys):
    plain = tmp_path / "plain.tif"
    with rasterio.open(plain, "w", driver="GTiff", width=64, height=64, count=1, dtype="uint8") as dst:
        dst.write(np.ones((1, 64, 64), np.uint8))
    with pytest.raises(InputError, match="not georeferenced"):
        open_ground_reference(plain)
    with pytest.raises(InputError, match="no such file"):
        open_ground_reference(tmp_path / "nope.tif")
    ortho, *_ = _reference(tmp_path, tiny_site)
    with pytest.raises(InputError, match="--reference-dem"):
        open_ground_reference(ortho, tmp_path / "nope_dem.tif")
    for argv in ([str(tiny_site), "--reference-ortho", str(plain)],
                 [str(tiny_site), "--reference-dem", str(ortho)]):
        assert view_main([*argv, "--out", str(tmp_path / "o"), "--port", "0"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "reference" in err[0], err
    assert not (tmp_path / "o").exists()


def _moved(src, dst, dx_m: float = 0.0, fill=None):
    """A copy of a raster shifted dx_m east (in its projected CRS), or filled with `fill`."""
    from affine import Affine

    with rasterio.open(src) as s:
        prof, a = s.profile, s.read()
    prof["transform"] = Affine.translation(dx_m, 0.0) * prof["transform"]
    if fill is not None:
        a = np.full(a.shape, fill, a.dtype)
    with rasterio.open(dst, "w", **prof) as d:
        d.write(a)
    return dst


def test_references_of_another_place_or_without_heights_are_refused(tiny_site, tmp_path, capsys):
    """As `aerec run --reference-dem` refuses them: an orthoimage or a DEM 1,500 km from the site
    (its GCPs, its images' footprints), a DEM that is all nodata."""
    ortho, dem_path, *_ = _reference(tmp_path, tiny_site)
    far_ortho = _moved(ortho, tmp_path / "far_ortho.tif", 1.5e6)
    far_dem = _moved(dem_path, tmp_path / "far_dem.tif", 1.5e6)
    nan_dem = _moved(dem_path, tmp_path / "nan_dem.tif", 0.0, fill=np.nan)
    for argv, name, words in (([far_ortho], "far_ortho.tif", "km from the site"),
                              ([ortho, "--reference-dem", far_dem], "far_dem.tif", "no height where the site is"),
                              ([ortho, "--reference-dem", nan_dem], "nan_dem.tif", "no height anywhere")):
        code = view_main([str(tiny_site), "--reference-ortho", *map(str, argv), "--out", str(tmp_path / "o"),
                          "--port", "0"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and name in err[0] and words in err[0], err
    assert not (tmp_path / "o").exists()


def _reopened(state, tmp_path, ref):
    """The viewer on a copy of a finished run's OUT with a ground reference, started and idle."""
    from aerec_viewer.app import ViewerApp

    out = tmp_path / "out"
    shutil.copytree(state.out, out, ignore=shutil.ignore_patterns(".aerec.lock"))
    app = ViewerApp(out, state.site.root, None, mode="reopen", port=0, update_hz=20.0, reference=ref)
    app.start()
    assert app.worker.done.wait(60)
    app.wait_idle()
    return app


def test_a_click_on_the_orthoimage_places_a_gcp_on_the_ground(tiny_run, tmp_path):
    state, _ = tiny_run
    ortho, dem_path, dem, crs, tf = _reference(tmp_path, state.site.root)
    ref = open_ground_reference(ortho, dem_path)
    app = _reopened(state, tmp_path, ref)
    try:
        gp = app.gcp_panel
        assert gp.image.options[-1] == ref.ortho.name
        app.call(lambda: (setattr(gp.zoom_click, "value", False), setattr(gp.walk, "value", False),
                          setattr(gp.image, "value", ref.ortho.name), gp.select_id(None)))
        app.wait_idle()                  # the list's change is applied (it clears the fields)
        app.call(lambda: setattr(gp.gid, "value", "ORTHO-1"))
        app.call(lambda: app.picking.show(wait=True))
        assert app.picking.plane.window.image == ref.ortho.name
        n_before = len(app.session.gcps)

        def click(col, row):
            p = app.picking.plane
            target = p.point_of(col, row)
            origin = target + np.array([3.0, -4.0, 40.0]) * p.render_width / 40.0
            return app.call(lambda: app.gcp.on_plane_click(origin, target - origin))

        assert click(40.0, 60.0) is not None
        g = app.session.get("ORTHO-1")
        lon, lat, h = ref.ground_at(40.0, 60.0)
        assert len(app.session.gcps) == n_before + 1 and not g.observations        # ground only
        assert (g.lon, g.lat, g.h) == pytest.approx((lon, lat, float(dem[60, 40])), abs=1e-7)
        assert gp.selected() == "ORTHO-1"
        # the working set's table: its role, no image placed yet, no residual; in bold, selected
        n_img = len(app.call(gp._registered_images))
        assert f"| **ORTHO-1** | control | 0 / {n_img} | - | - |" in gp.listing.content
        # selected: a second click moves it
        click(45.0, 61.0)
        g = app.session.get("ORTHO-1")
        assert (g.lon, g.lat) == pytest.approx(ref.ground_at(45.0, 61.0)[:2], abs=1e-9)
        assert g.h == pytest.approx(float(dem[61, 45]), abs=1e-4)
        # its ground position is marked on the orthoimage, where it was clicked
        marks = app.call(app.marks.marker_positions)
        pos = marks["/gcp/plane_marks/ORTHO-1"][0]
        assert np.allclose(pos[:2], app.picking.plane.point_of(45.0, 61.0)[:2], atol=1e-6 * app.picking.plane.render_width)
        # the orthoimage is no image of the site: no prediction there, no observation recorded
        with pytest.raises(GcpError, match="ground positions"):
            app.call(gp._predict)
        # with "Then its next image", a new GCP placed on the orthoimage sends the plane back to
        # the site image shown before it (where the operator places it next)
        first = sorted(app.session.images)[1]
        app.call(lambda: (setattr(gp.image, "value", first), setattr(gp.walk, "value", True)))
        app.call(gp.new_on_reference)                          # the G key
        assert gp.selected() is None and gp.image.value == ref.ortho.name
        app.call(lambda: app.picking.show(wait=True))
        ids = set(app.session.ids)
        click(80.0, 30.0)
        new, = set(app.session.ids) - ids
        assert gp.selected() == new and gp.image.value == first
    finally:
        app.stop()


def _roof_reference(tmp_path, site, cell_m: float = 5.0):
    """A 5 m DEM of flat ground at 100 m with a 9 m block (a building its cells smooth), and a
    0.5 m orthoimage over it, in the site's CRS, around the site's first GCP."""
    from affine import Affine

    with rasterio.open(site / "gt_dsm.tif") as src:
        crs, tf = src.crs, src.transform
    e0, n0 = tf.c, tf.f
    dem = np.full((40, 40), 100.0, np.float32)
    dem[10:14, 10:14] = 109.0                              # 20 m x 20 m, its corner at cell (10, 10)
    dem_path, ortho = tmp_path / "dem5.tif", tmp_path / "ortho05.tif"
    with rasterio.open(dem_path, "w", driver="GTiff", width=40, height=40, count=1, dtype="float32",
                       crs=crs, transform=Affine(cell_m, 0, e0, 0, -cell_m, n0)) as dst:
        dst.write(dem[None])
    with rasterio.open(ortho, "w", driver="GTiff", width=400, height=400, count=1, dtype="uint8",
                       crs=crs, transform=Affine(cell_m / 10, 0, e0, 0, -cell_m / 10, n0)) as dst:
        dst.write(np.random.default_rng(0).integers(0, 255, (1, 400, 400)).astype(np.uint8))
    return open_ground_reference(ortho, dem_path)


def test_a_dem_height_at_a_roof_corner_is_doubtful(tiny_site, tmp_path):
    """A roof corner clicked on the orthoimage: the 5 m DEM gives it a height between the roof's
    and the ground's; within three quarters of the DEM's cells it changes by metres: the height is
    doubtful, its sigma half that change. Flat ground far from the block is not."""
    ref = _roof_reference(tmp_path, tiny_site)
    lon, lat, h = ref.ground_at(101.5, 101.5)                # 0.75 m inside the roof's corner
    assert 100.0 < h < 109.0
    doubt = ref.height_doubt(lon, lat)
    assert doubt.cell_m == pytest.approx(5.0) and not doubt.flat and doubt.spread_m > 4.0
    assert doubt.sigma_m == pytest.approx(doubt.spread_m / 2)
    lon, lat, _ = ref.ground_at(300.0, 300.0)                # open ground
    assert ref.height_doubt(lon, lat).flat


def test_a_doubtful_height_is_flagged_and_the_images_give_it(tiny_run, tmp_path):
    """In the viewer: a GCP placed on the orthoimage at a roof corner is flagged before any
    upgrade (its sigma, on its marker and in the upgrade's list); a control GCP 8 m low that says
    so gets its height from the images: "Take the images' height" puts it within 0.5 m, with the
    images' own sigma."""
    from aerec_viewer.gcp_session import edit_gcp
    from aerec_viewer.results import run_upgrade

    state, _ = tiny_run
    assert sum(im.view is not None for im in state.site.images) >= 2
    ref = _roof_reference(tmp_path, state.site.root)
    app = _reopened(state, tmp_path, ref)
    try:
        gp = app.gcp_panel
        app.call(lambda: (setattr(gp.zoom_click, "value", False), setattr(gp.walk, "value", False),
                          setattr(gp.image, "value", ref.ortho.name), gp.select_id(None)))
        app.wait_idle()
        app.call(lambda: setattr(gp.gid, "value", "ROOF-1"))
        app.call(lambda: app.picking.show(wait=True))
        p = app.picking.plane
        target = p.point_of(101.5, 101.5)
        origin = target + np.array([0.0, 0.0, 40.0]) * p.render_width / 40.0
        app.call(lambda: app.gcp.on_plane_click(origin, target - origin))
        g = app.session.get("ROOF-1")
        assert g.sigma_h_m is not None and g.sigma_h_m > 2.0
        assert "known only to" in gp.info.content and not gp.take_height.disabled
        marks = app.call(app.marks.marker_positions)
        assert "h +-" in marks["/gcp/plane_marks/ROOF-1"][2]
        assert "height known only to" in app.g_ready_list.content
        # a typed height is the operator's: no longer doubtful
        app.call(lambda: edit_gcp(app.session, "ROOF-1", x=g.lon, y=g.lat, h=g.h + 3.0))
        assert app.session.get("ROOF-1").sigma_h_m is None

        # a control GCP of the run, 8 m low, says so; the images give its height
        ctrl = [x for x in app.session.gcps if x.role == "control" and len(x.observations) >= 2]
        true_h = ctrl[0].h
        app.call(lambda: edit_gcp(app.session, ctrl[0].id, x=ctrl[0].lon, y=ctrl[0].lat,
                                  h=true_h - 8.0, sigma_h_m=4.0))
        app.call(lambda: setattr(app.gcp, "upgrade", run_upgrade(app.session, app.models, app.cfg,
                                                             {im.name: im for im in app.site.images})))
        app.call(lambda: gp.select_id(ctrl[0].id))
        app.wait_idle()
        h = app.call(gp.take_images_height)
        assert abs(h - true_h) < 0.5, (h, true_h)
        # it stays flagged unless the images know it to 0.3 m; then with their sigma, not the DEM's
        sig = app.session.get(ctrl[0].id).sigma_h_m
        assert sig is None or sig < 1.0, sig
    finally:
        app.stop()
