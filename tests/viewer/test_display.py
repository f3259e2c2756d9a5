"""The viewer's display maths without a server: frames, transforms, the picking plane, point
sizes and colours, the loupe's texture, contrast, the DSM preview and the evaluation's markdown."""

from __future__ import annotations

import numpy as np
import pytest

from aerec_viewer import display as dp
from aerec_viewer.picking import PickPlane, layout_pick_plane, pixel_from_ray
from recon_core.model.tiling import Window as ImageWindow


def random_rotation(rng) -> np.ndarray:
    q = rng.normal(size=4)
    return dp.quat_to_matrix(q / np.linalg.norm(q))


def test_quaternion_round_trip():
    rng = np.random.default_rng(1)
    for _ in range(20):
        R = random_rotation(rng)
        assert np.allclose(dp.quat_to_matrix(dp.matrix_to_quat(R)), R, atol=1e-12)


def test_pixel_from_ray_exact_on_a_known_pose():
    """A ray through a known pixel of a tilted, rotated image plane gives that pixel back."""
    rng = np.random.default_rng(2)
    win = ImageWindow("a.tif", 300, 200, 640, 480)
    plane = PickPlane(win, np.array([12.0, -7.0, 3.0]), dp.matrix_to_quat(random_rotation(rng)),
                      64.0, 48.0)
    for col, row in [(300.0, 200.0), (-0.5 + 300, -0.5 + 200), (939.5, 679.5), (517.25, 333.75)]:
        target = plane.point_of(col, row)
        origin = target + rng.normal(size=3) * 50.0
        got = pixel_from_ray(plane, origin, target - origin)
        assert got is not None
        assert abs(got[0] - col) < 1e-6 and abs(got[1] - row) < 1e-6
    # a ray pointing away from the plane, or hitting it beside the image, misses
    t = plane.point_of(400, 300)
    o = t + 20.0 * dp.quat_to_matrix(plane.wxyz)[:, 2]
    assert pixel_from_ray(plane, o, t - o) is not None and pixel_from_ray(plane, o, o - t) is None
    far = plane.point_of(win.col0 + 3 * win.width, 300)
    assert pixel_from_ray(plane, far + (o - t), t - o) is None


def test_plane_follows_the_viser_image_convention():
    """Local frame of scene.add_image: pixel (0, 0) at (-w/2, -h/2, 0), +x right, +y down."""
    w, h = 10.0, 6.0
    pos = np.zeros(3)
    ident = np.array([1.0, 0.0, 0.0, 0.0])
    f = dp.plane_hit([-w / 2, -h / 2, 5.0], [0, 0, -1.0], position=pos, wxyz=ident,
                     render_width=w, render_height=h)
    assert np.allclose(f, (0.0, 0.0))
    f = dp.plane_hit([w / 4, h / 4, 5.0], [0, 0, -1.0], position=pos, wxyz=ident,
                     render_width=w, render_height=h)
    assert np.allclose(f, (0.75, 0.75))
    # the flat pose shows image rows going south (display -y) when seen from above
    top = dp.plane_point(0.5, 0.0, position=pos, wxyz=dp.FLAT_WXYZ, render_width=w, render_height=h)
    bottom = dp.plane_point(0.5, 1.0, position=pos, wxyz=dp.FLAT_WXYZ, render_width=w, render_height=h)
    assert top[1] > bottom[1]


def test_image_window_pixels_follow_site_format():
    win = ImageWindow("a.tif", 100, 50, 200, 100)
    assert win.pixel(0.0, 0.0) == (99.5, 49.5)           # left/top edge of pixel (100, 50)
    assert np.allclose(win.pixel(*win.fraction(123.25, 77.5)), (123.25, 77.5))


def test_the_euclidean_display_is_the_upgrade_map_with_its_metric_warp():
    """With the metric bend step's warp, the 3D view places points where the DSM stage does
    (recon_core.geometry.enu_map.EnuMap), and a click's inverse finds the frame point back."""
    from aerec_viewer.display import euclidean_display_transform
    from recon_core.geometry.enu_map import BendWarp, EnuMap

    rng = np.random.default_rng(1)
    X = rng.uniform(-500, 500, size=(200, 3)) * [1, 1, 0.05]
    warp = BendWarp(np.zeros(3), np.eye(3) / 500.0, np.eye(3)[:2], np.zeros(3),
                    np.array([0.002, -0.001, 0.001, 0.001, 0.0, -0.002, 0, 0, 0]))
    assert np.abs(warp(X)).max() > 0.1
    H = np.vstack([np.hstack([0.5 * np.eye(3) + 0.01 * rng.normal(size=(3, 3)), rng.normal(size=(3, 1))]),
                   [0, 0, 0, 1]])
    T = euclidean_display_transform(H, np.array([55.0, -21.0, 10.0]), warp)
    np.testing.assert_allclose(T.apply(X), EnuMap(H, warp)(X), atol=1e-3)     # float32 display
    np.testing.assert_allclose(T.inverse(EnuMap(H, warp)(X)), X, atol=1e-9)
    plain = euclidean_display_transform(H, np.array([55.0, -21.0, 10.0]))
    assert np.abs(plain.apply(X) - T.apply(X)).max() > 0.05
    # and with the bend fitted to control GCPs after H_A (recon_core.bend.gcp)
    from recon_core.geometry.enu_map import EnuWarp

    post = EnuWarp(np.array([10.0, -5.0]), 300.0, np.array([0.3, -0.2, 0.1, 0.0, 0.2, 0.1, 1.5, -0.8, 1.2]))
    T2 = euclidean_display_transform(H, np.array([55.0, -21.0, 10.0]), warp, post)
    full = EnuMap(H, warp, post)
    assert np.abs(full(X) - EnuMap(H, warp)(X)).max() > 0.5
    np.testing.assert_allclose(T2.apply(X), full(X), atol=1e-3)
    np.testing.assert_allclose(T2.inverse(full(X)), X, atol=1e-6)


def test_affine_display_transform_is_image_aligned_and_not_mirrored():
    rng = np.random.default_rng(3)
    E = np.column_stack([rng.uniform(-500, 500, 2000), rng.uniform(-500, 500, 2000), np.zeros(2000)])
    E[:, 2] = 30 * np.sin(E[:, 0] / 120.0) + rng.normal(0, 1, 2000)
    H = np.hstack([rng.normal(size=(3, 3)), rng.normal(size=(3, 1)) * 100])   # arbitrary gauge
    X = E @ H[:, :3].T + H[:, 3]
    cam_e = np.array([[0.5, 0.0, 0.05, 400.0], [0.0, -0.5, 0.1, 300.0]])       # ~nadir, north up
    Hi = np.linalg.inv(np.vstack([H, [0, 0, 0, 1]]))
    cam = cam_e @ Hi                                     # the same camera in the affine frame
    T = dp.affine_display_transform(X, cam)
    Y = T.apply(X).astype(np.float64)
    assert np.linalg.det(T.A) > 0 and T.kind == "affine"
    assert np.allclose(T.inverse(Y), X, atol=1e-3 * np.abs(X).max())
    pix = np.c_[X, np.ones(len(X))] @ cam.T
    assert np.allclose(Y[:, 0] - Y[:, 0].mean(), pix[:, 0] - pix[:, 0].mean(), atol=1e-2)
    assert np.allclose(Y[:, 1] - Y[:, 1].mean(), -(pix[:, 1] - pix[:, 1].mean()), atol=1e-2)
    span_xy = np.percentile(Y[:, 0], 95) - np.percentile(Y[:, 0], 5)
    span_z = np.percentile(Y[:, 2], 95) - np.percentile(Y[:, 2], 5)
    assert 0.1 < span_z / span_xy < 0.2                # relief visible, not dominant
    # the display height follows the true height (up to the depth-reversal sign)
    assert abs(np.corrcoef(Y[:, 2], E[:, 2])[0, 1]) > 0.95
    # refitting on a flatter-looking subset keeps x, y and the origin
    T2 = dp.refine_affine_transform(T, X[::3])
    assert np.allclose(T2.A[:2], T.A[:2]) and np.allclose(T2.inverse(np.zeros((1, 3))),
                                                          T.inverse(np.zeros((1, 3))))


def test_image_footprint_projects_to_the_image_corners():
    rng = np.random.default_rng(4)
    X = rng.normal(size=(200, 3)) * [300, 300, 10]
    cam = np.array([[1.0, 0.02, -0.03, 500.0], [0.01, 1.0, -0.01, 400.0]])
    T = dp.affine_display_transform(X, cam)
    fp = dp.image_footprint(T, cam, 1000, 800, z=2.0)
    pix = np.c_[T.inverse(fp), np.ones(4)] @ cam.T
    assert np.allclose(pix, [[-0.5, -0.5], [999.5, -0.5], [999.5, 799.5], [-0.5, 799.5]], atol=1e-6)
    assert np.allclose(fp[:, 2], 2.0)


def test_keep_mask_is_nested_and_proportional():
    ids = np.arange(200_000)
    a, b = dp.keep_mask(ids, 0.3), dp.keep_mask(ids, 0.1)
    assert np.all(a[b]) and abs(a.mean() - 0.3) < 0.01 and abs(b.mean() - 0.1) < 0.01
    assert dp.keep_mask(ids, 1.0).all()
    # different salts are independent (a thinned store and a display subsample of another
    # cloud never conspire to show nothing)
    c = dp.keep_mask(ids, 0.5, salt=1) & dp.keep_mask(ids, 0.5, salt=2)
    assert abs(c.mean() - 0.25) < 0.01
    # a display subsample of a thinned store, with the store's salt, keeps the asked fraction
    stored = ids[dp.keep_mask(ids, 0.5, salt=3)]
    shown = dp.keep_mask(stored, 0.025 * 0.5, salt=3)
    assert abs(shown.mean() - 0.025) < 0.003
    assert dp.display_fraction(1000, 2000) == 1.0 and dp.display_fraction(4000, 1000) == 0.25


def test_points_about_tile_the_footprint_whatever_the_budget():
    """The drawing cost in software WebGL is the fragments: the automatic point size makes the
    points shown cover the footprint about once (not four times over, as 1/200 of the extent
    did at 150 k points on a 600 m site), and a sparse cloud keeps the 1/200 cap."""
    ext, area = 600.0, 600.0 * 600.0
    for n in (40_000, 150_000, 600_000):
        s = dp.auto_point_size(ext, area, n)
        cover = n * s * s / area
        assert 0.7 < cover < 1.45, (n, s, cover)
    assert dp.auto_point_size(ext, area, 150_000) < 0.6 * ext / 200
    assert dp.auto_point_size(ext, area, 2_000) == ext / 200          # sparse: capped
    assert dp.auto_point_size(ext, 0.0, 10) == ext / 200 and dp.auto_point_size(ext, area, 0) == ext / 200
    # quantised: a cloud growing from 100 k to 200 k points in 1 % steps resizes its points twice
    sizes = {dp.auto_point_size(ext, area, int(100_000 * 1.01 ** k)) for k in range(70)}
    assert len(sizes) <= 3


def test_union_area_counts_overlapping_groups_once():
    from aerec_viewer.scene import union_area

    a = (np.array([0.0, 0.0]), np.array([100.0, 100.0]))
    side = (np.array([200.0, 0.0]), np.array([300.0, 100.0]))        # the affine frame: side by side
    half = (np.array([50.0, 0.0]), np.array([150.0, 100.0]))
    assert np.isclose(union_area([a]), 1e4, rtol=0.02)
    assert np.isclose(union_area([a, a, a]), 1e4, rtol=0.02)           # Euclidean: on top
    assert np.isclose(union_area([a, side]), 2e4, rtol=0.02)
    assert np.isclose(union_area([a, half]), 1.5e4, rtol=0.02)
    assert union_area([]) == 0.0


def test_closest_point_to_ray_picks_the_point_under_the_cursor():
    P = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, -100.0]])
    o = np.array([10.2, 0.1, 100.0])
    assert dp.closest_point_to_ray(P, o, np.array([0.0, 0.0, -1.0])) == 1
    assert dp.closest_point_to_ray(P, o, np.array([0.0, 0.0, 1.0])) is None    # all behind
    assert dp.closest_point_to_ray(P, o + [500, 0, 0], np.array([0.0, 0.0, -1.0])) is None


def test_quad_image_places_the_parallelogram_exactly():
    C = np.array([[0.0, 0.0, 0.0], [10.0, 1.0, 0.5], [12.0, -7.0, 1.0], [2.0, -8.0, 0.5]])
    tex = np.full((40, 50), 200, np.uint8)
    q = dp.quad_image(C, tex, max_side=100)
    R = dp.quat_to_matrix(q.wxyz)
    local = (C - q.position) @ R                       # corners in the image's local frame
    assert np.allclose(local[:, 2], 0.0, atol=1e-9)
    assert np.all(np.abs(local[:, 0]) <= q.render_width / 2 + 1e-9)
    assert np.all(np.abs(local[:, 1]) <= q.render_height / 2 + 1e-9)
    H, W = q.rgba.shape[:2]
    for (x, y, _), towards in zip(local, [(1, 1), (-1, 1), (-1, -1), (1, -1)]):
        u = (x / q.render_width + 0.5) * W + towards[0] * 2
        v = (y / q.render_height + 0.5) * H + towards[1] * 2
        assert q.rgba[int(np.clip(v, 0, H - 1)), int(np.clip(u, 0, W - 1)), 3] == 255
    assert (q.rgba[..., 3] == 0).any()                 # outside the parallelogram: transparent


def test_point_colours_cover_every_mode():
    rng = np.random.default_rng(5)
    n = 50
    args = (rng.integers(0, 255, (n, 3)).astype(np.uint8), rng.normal(size=n),
            rng.integers(2, 6, n).astype(np.float32), rng.random(n).astype(np.float32))
    r = dp.color_ranges(args[1], args[2], args[3])
    for mode in dp.COLOR_MODES:
        c = dp.point_colors(mode, *args, r)
        assert c.shape == (n, 3) and c.dtype == np.uint8


def test_pick_plane_layout_sits_beside_the_cloud():
    win = ImageWindow("a.tif", 0, 0, 2000, 1000)
    p = layout_pick_plane(win, (np.array([-10.0, -5.0, -1.0]), np.array([10.0, 5.0, 1.0])))
    assert p.position[0] - p.render_width / 2 > 10.0
    assert np.isclose(p.render_height / p.render_width, 0.5)


def test_loupe_texture_enlarges_pixels_and_leaves_the_aimed_pixel_clear():
    from aerec_viewer.picking import LOUPE_CROSS, loupe_texture, loupe_window

    win = loupe_window(500, 300, "a.tif", 3.2, 297.0, size=40)     # shifted inside at the corner
    assert (win.col0, win.row0, win.width, win.height) == (0, 260, 40, 40)
    gray = np.arange(40 * 40, dtype=np.uint16).reshape(40, 40).astype(np.uint8)
    tex = loupe_texture(gray, win, (12.0, 280.0), scale=8)
    assert tex.shape == (320, 320, 3)
    cross = np.all(tex == LOUPE_CROSS, axis=2)
    # a pixel is an 8 x 8 block of one value where the cross does not pass
    assert np.all(tex[0:8, 0:8] == gray[0, 0]) and np.all(tex[8:16, 24:32] == gray[1, 3])
    # the cross runs through the centre of pixel (12, 20) of the window, open around it
    cy, cx = 20 * 8 + 4, 12 * 8 + 4
    assert cross[cy, :cx - 12].all() and cross[:cy - 12, cx].all() and cross[cy + 13:, cx].all()
    assert not cross[cy - 8:cy + 9, cx - 8:cx + 9].any()
    assert cross.sum() < 2 * 320


def test_contrast_modes_stretch_a_dark_image(tmp_path):
    """A dark 16-bit image among bright ones: with the site's shared stretch it is nearly black;
    the "image" and "window" contrast modes give it the full range."""
    from aerec_viewer.imagery import ImageSource
    from recon_core.io.site import open_image
    from recon_core.model.tiling import Window
    from tests.conftest import write_tiff

    rng = np.random.default_rng(0)
    bright = rng.integers(0, 2047, (64, 80), dtype=np.uint16)
    write_tiff(tmp_path / "a.tif", bright)
    write_tiff(tmp_path / "b.tif", (bright // 20).astype(np.uint16))          # dark
    src = ImageSource([open_image(tmp_path / "a.tif"), open_image(tmp_path / "b.tif")])
    win = Window("b.tif", 0, 0, 80, 64)
    site, own, local = (src.read(win, 256, m).astype(float) for m in ("site", "image", "window"))
    assert site.max() < 100 and own.std() > 2 * site.std() and local.std() > 2 * site.std()
    with pytest.raises(ValueError):
        src.read(win, 256, "loud")


def test_dsm_preview_reads_a_big_dsm_through_its_overviews(tmp_path, monkeypatch):
    """The panel's preview of a DSM (a COG, as the pipeline writes it) is read near the panel's
    size, never whole, and its colours still follow the relief (a ramp from west to east)."""
    import rasterio.io

    from aerec_viewer.results import dsm_preview
    from recon_core.io.raster import Grid, write_dsm

    g = Grid(32631, 500000.0, 4000000.0, 0.5, 4000, 3000)
    H = 100.0 + 0.01 * np.arange(g.width, dtype=np.float32)[None, :].repeat(g.height, 0)
    H[:300, :300] = np.nan
    p = write_dsm(tmp_path / "dsm.tif", H, g)
    shapes = []
    read = rasterio.io.DatasetReader.read

    def spy(self, *a, **k):
        shapes.append(k.get("out_shape"))
        return read(self, *a, **k)

    monkeypatch.setattr(rasterio.io.DatasetReader, "read", spy)
    img = dsm_preview(p, max_side=640)
    assert shapes and all(s is not None and s[0] * s[1] <= 1280 * 1280 for s in shapes), shapes
    assert img.ndim == 3 and img.shape[2] == 3 and max(img.shape[:2]) <= 640 + 200
    row = img[img.shape[0] // 2, 40:440].astype(float).mean(axis=1)
    assert abs(row[-1] - row[0]) > 5                          # colours follow the height


def test_eval_markdown_shows_each_group_and_the_same_cells_comparison():
    """The Results tab's table: the fused figures, then each date group alone and the fused DSM
    against it on the cells both cover; an eval without groups (one group, or an old
    eval.json) shows only the fused figures."""
    from aerec_viewer.results import eval_markdown

    ev = {"aligned": {"median_abs_err_m": 0.677, "completeness_pct": 57.6, "rmse_m": 5.2},
          "alignment": {"dx_m": -1.6, "dy_m": 0.7, "dz_m": -0.4},
          "groups": {"1": {"aligned": {"median_abs_err_m": 0.613, "completeness_pct": 52.0},
                           "fused_vs_group_same_cells": {"cells": 10, "a": {"median_abs_err_m": 0.606},
                                                         "b": {"median_abs_err_m": 0.611}}},
                     "0": {"aligned": {"median_abs_err_m": 0.952, "completeness_pct": 41.9}},
                     "2": {"error": "too few cells"}}}
    md = eval_markdown(ev)
    assert "| 0.677 m |" in md.replace("| median abs. height error ", "")
    rows = [line for line in md.splitlines() if line.startswith("| 0 |") or line.startswith("| 1 |")]
    assert rows == ["| 0 | 0.952 | 41.9 % |  |", "| 1 | 0.613 | 52.0 % | 0.606 / 0.611 |"]
    assert "group alone" in md
    assert "group alone" not in eval_markdown({k: v for k, v in ev.items() if k != "groups"})
    # the DSM scored by how many date groups agree at each cell
    assert "groups agreeing" not in md
    ev["by_agreement"] = {"classes": {"2": {"cells_pct_of_gt": 30.1, "median_abs_err_m": 0.41, "within_pct": 88.0},
                                      "0": {"cells_pct_of_gt": 2.0, "median_abs_err_m": 1.9, "within_pct": 25.0},
                                      "1": {"cells_pct_of_gt": 25.5, "median_abs_err_m": 1.25, "within_pct": 41.0}}}
    md = eval_markdown(ev)
    rows = md.split("groups agreeing")[1].splitlines()[2:5]
    assert rows == ["| 0 (weak pair, filled) | 2.0 % | 1.900 | 25.0 % |", "| 1 | 25.5 % | 1.250 | 41.0 % |",
                    "| 2 | 30.1 % | 0.410 | 88.0 % |"]

