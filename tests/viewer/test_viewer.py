"""The viewer without a browser: display maths, the worker, GCP editing, and a headless server
running the real pipeline on a small site (points grow, tiles appear, progress ends, GCP picks
through the click handlers' own functions, upgrade, saved GeoJSON, reopening)."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from aerec_viewer import display as dp
from aerec_viewer.app import MARK_RING_PX
from aerec_viewer.gcp_panel import PickPlane, layout_pick_plane, pixel_from_ray
from aerec_viewer.gcp_session import (
    GcpError,
    add_observation,
    delete_gcp,
    edit_gcp,
    import_site_gcps,
    new_gcp,
    open_session,
    redo,
    remove_observation,
    set_affine_position,
    undo,
)
from aerec_viewer.worker import ReconWorker
from recon_core.events import (
    BundleAdjusted,
    Message,
    ModelUpdated,
    PointsAdded,
    StageProgress,
    TileRegistered,
)
from recon_core.model.tiling import Window as ImageWindow


# -- display maths --------------------------------------------------------------------------
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
    from recon_core.geometry.enu_map import EnuMap
    from recon_core.geometry.pushbroom import BendWarp

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
    # and with the bend fitted to control GCPs after H_A (recon_core.euclidean.gcp_bend)
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


# -- the worker -----------------------------------------------------------------------------
def tile_event(k: int, total: int = 4) -> TileRegistered:
    cam = np.array([[1.0, 0.01, -0.02, 3.0 * k], [0.0, 1.0, -0.01, 1.0]])
    fp = np.array([[0, 0, 0], [100, 0, 0], [100, -100, 0], [0, -100, 0]], float) + [50 * k, 0, 0]
    return TileRegistered(0, f"a.tif:0_{k}", "a.tif", cam, fp, 40, k, total)


def points_event(start: int, n: int, kind: str = "sparse") -> PointsAdded:
    rng = np.random.default_rng(start)
    ids = np.arange(start, start + n)
    return PointsAdded(0, ids, rng.normal(size=(n, 3)) * [100, 100, 5],
                       np.full((n, 3), 128, np.uint8), np.full(n, 2), rng.random(n), kind)


def test_worker_folds_events_into_a_display_state():
    w = ReconWorker(None, "/nonexistent")
    w.handle(StageProgress("features", 1, 3, "a.tif", 0))
    w.handle(tile_event(0))
    w.handle(tile_event(1))
    w.handle(points_event(0, 100))
    v1 = w.snapshot()
    assert v1.groups[0].sparse.n == 100 and len(v1.groups[0].tiles) == 2
    assert v1.groups[0].transform is not None and v1.stage == "sfm" and v1.stage_done == 2
    w.handle(points_event(100, 50))
    w.handle(BundleAdjusted(0, "global", 10.0, 2.0, 0.3, 2, 150, 0.1))
    s = w.snapshot()
    assert len(s.groups[0].sparse.batches) == 2 and s.groups[0].ba["rms_px"] == 0.3
    T = s.groups[0].transform
    ev = points_event(0, 140)
    w.handle(ModelUpdated(0, {"a.tif:0_0": tile_event(0).camera}, {"a.tif:0_0": tile_event(0).footprint},
                          ev.ids, ev.xyz, ev.rgb, ev.n_views, ev.reproj_px))
    s2 = w.snapshot()
    assert s2.groups[0].sparse.generation == s.groups[0].sparse.generation + 1
    assert s2.groups[0].sparse.n == 140
    T2 = s2.groups[0].transform          # horizontal axes and origin fixed once; relief refit
    assert np.allclose(T2.A[:2], T.A[:2]) and np.allclose(T2.b[:2], T.b[:2])
    assert np.allclose(T2.inverse(np.zeros((1, 3))), T.inverse(np.zeros((1, 3))))
    assert s2.groups[0].tiles["a.tif:0_0"].version == 1
    w.handle(points_event(0, 30, kind="dense"))
    w.handle(Message("warning", "hello", 0))
    w.handle(object())                                     # an event type from the future
    s3 = w.snapshot()
    assert s3.groups[0].dense.n == 30 and ("warning", "hello") in s3.messages
    assert s3.version > s2.version and v1.groups[0].sparse.n == 100   # snapshots are immutable


def test_dense_store_thins_beyond_its_cap():
    w = ReconWorker(None, "/nonexistent")
    w.handle(tile_event(0))
    w._groups[0].dense.cap = 1000
    for k in range(5):
        w.handle(points_event(k * 500, 500, kind="dense"))
    d = w.snapshot().groups[0].dense
    assert d.n <= 1000 and d.kept_fraction < 1.0 and d.n > 300


def test_pause_blocks_the_pipeline_thread_until_resume():
    w = ReconWorker(None, "/nonexistent")
    w.pause()
    done = threading.Event()

    def pipeline():
        w.handle(tile_event(0))
        done.set()

    threading.Thread(target=pipeline, daemon=True).start()
    assert not done.wait(0.5)
    assert w.snapshot().groups[0].tiles                    # the event was folded, then held
    w.resume()
    assert done.wait(2.0)


def test_two_million_points_stay_within_the_point_budget():
    """A dense cloud growing to 2 M points: the scene shows at most ~1.5 x the budget, in few
    chunk nodes, and every update stays cheap (the full cloud stays in the worker / on disk)."""
    import viser

    from aerec_viewer.imagery import ImageSource
    from aerec_viewer.scene import SceneView

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        w = ReconWorker(None, "/nonexistent")
        w.handle(tile_event(0))
        w.handle(points_event(0, 2000))
        sv = SceneView(server, ImageSource([]))
        sv.settings.budget = 100_000
        worst = 0.0
        for k in range(20):
            w.handle(points_event(10_000 + k * 100_000, 100_000, kind="dense"))
            snap = w.snapshot()
            t0 = time.time()
            sv.sync(snap, {0: snap.groups[0].transform})
            worst = max(worst, time.time() - t0)
            assert sv.displayed_points() <= 1.5 * sv.settings.budget + 2000
        assert snap.groups[0].dense.n == 2_000_000
        assert sv.displayed_points() >= 0.5 * sv.settings.budget
        assert sum(len(st.chunks) for st in sv._clouds.values()) <= 20
        assert worst < 5.0
    finally:
        server.stop()


# -- GCP editing ----------------------------------------------------------------------------
class _Img:
    def __init__(self, name, w, h):
        self.name, self.width, self.height = name, w, h


def test_gcp_session_edits_are_saved_atomically_and_restored(small_site, tmp_path):
    from recon_core.io.gcps import read_gcps_geojson
    from recon_core.io.site import load_site

    site = load_site(small_site)
    out = tmp_path / "out"
    s = open_session(out, site)
    assert s.ids == ["G1"] and (out / "gcps.geojson").exists()
    assert not (small_site / "gcps.geojson").read_text().count("written_by")   # site untouched
    g = new_gcp(s, x=10.0001, y=45.0002, h=120.0, role="check")
    assert g.id == "GCP-01"
    add_observation(s, "GCP-01", "a.tif", 10.25, 20.5)
    add_observation(s, "GCP-01", "b.tif", 11.0, 21.0)
    with pytest.raises(GcpError):
        add_observation(s, "GCP-01", "a.tif", 64.0, 3.0)   # outside the 64 x 48 image
    with pytest.raises(GcpError):
        new_gcp(s, "G1", x=0.0, y=0.0, h=0.0)              # duplicate id
    set_affine_position(s, "G1", 0, np.array([1.0, 2.0, 3.0]))
    edit_gcp(s, "GCP-01", new_id="P7", role="control")
    remove_observation(s, "P7", "b.tif")
    # what the core reads back
    gcps = read_gcps_geojson(out / "gcps.geojson", {im.name: im for im in site.images})
    by = {x.id: x for x in gcps}
    assert by["P7"].observations == {"a.tif": (10.25, 20.5)} and by["P7"].role == "control"
    # reopening restores everything, picked positions included
    s2 = open_session(out, site)
    assert s2.ids == ["G1", "P7"] and np.allclose(s2.get("G1").affine_picked[0], [1, 2, 3])
    delete_gcp(s2, "G1")
    assert open_session(out, site).ids == ["P7"]
    assert import_site_gcps(s2) == ["G1"]                 # back from the site's list


def test_every_gcp_edit_can_be_undone_and_redone(small_site, tmp_path):
    """Undo walks back through observations, moves, role changes, cloud picks and deletes, each
    written to OUT/gcps.geojson; a new edit after an undo drops the redo history."""
    from recon_core.io.site import load_site

    site = load_site(small_site)
    out = tmp_path / "out"
    s = open_session(out, site)
    with pytest.raises(GcpError):
        undo(s)                                             # nothing yet
    add_observation(s, "G1", "a.tif", 10.0, 20.0)
    add_observation(s, "G1", "a.tif", 12.0, 22.0)           # a move
    edit_gcp(s, "G1", role="check")
    set_affine_position(s, "G1", 0, np.array([1.0, 2.0, 3.0]))
    delete_gcp(s, "G1")
    assert s.ids == []
    assert undo(s) == "delete G1" and s.ids == ["G1"]
    assert 0 in s.get("G1").affine_picked
    assert undo(s).startswith("pick G1") and not s.get("G1").affine_picked
    assert undo(s) == "edit G1" and s.get("G1").role == "control"
    assert undo(s).startswith("move") and s.get("G1").observations["a.tif"] == (10.0, 20.0)
    assert open_session(out, site).get("G1").observations["a.tif"] == (10.0, 20.0)   # on disk
    assert redo(s).startswith("move") and s.get("G1").observations["a.tif"] == (12.0, 22.0)
    remove_observation(s, "G1", "a.tif")                    # a new edit: no more redo
    with pytest.raises(GcpError):
        redo(s)
    assert undo(s).startswith("remove") and "a.tif" in s.get("G1").observations
    # an edit that fails changes nothing and records nothing
    v = s.version
    with pytest.raises(GcpError):
        edit_gcp(s, "G1", new_id="P9", role="bogus")
    assert s.ids == ["G1"] and s.version == v


def test_a_new_gcp_cannot_reuse_another_gcps_ground_coordinates(small_site, tmp_path):
    from recon_core.io.site import load_site

    s = open_session(tmp_path / "out", load_site(small_site))
    g = s.get("G1")
    with pytest.raises(GcpError, match="already has these ground coordinates"):
        new_gcp(s, x=g.lon, y=g.lat, h=g.h)
    assert s.ids == ["G1"]


def test_gcp_from_projected_coordinates(small_site, tmp_path):
    from recon_core.geometry.geodesy import geodetic_to_projected
    from recon_core.io.site import load_site

    s = open_session(tmp_path / "out", load_site(small_site))
    e, n, h = geodetic_to_projected(np.array([10.5, 45.25, 300.0]), 32632)
    g = new_gcp(s, "U1", x=e, y=n, h=h, epsg=32632)
    assert abs(g.lon - 10.5) < 1e-8 and abs(g.lat - 45.25) < 1e-8 and abs(g.h - 300.0) < 1e-6
    with pytest.raises(GcpError):
        new_gcp(s, "U2", x=500000.0, y=4e6, h=0.0)         # E/N without an EPSG code


def test_pick_plane_layout_sits_beside_the_cloud():
    win = ImageWindow("a.tif", 0, 0, 2000, 1000)
    p = layout_pick_plane(win, (np.array([-10.0, -5.0, -1.0]), np.array([10.0, 5.0, 1.0])))
    assert p.position[0] - p.render_width / 2 > 10.0
    assert np.isclose(p.render_height / p.render_width, 0.5)


# -- a headless server running the real pipeline --------------------------------------------
def _small_site(tmp_root: Path) -> tuple[Path, object]:
    """The synthetic tiny site when the generator works, else the real pair (tile 400)."""
    from recon_core.config import preset

    try:
        from recon_core.synthetic.generator import generate_site

        site = tmp_root / "tiny_site"
        generate_site(site, "tiny", seed=0)
        return site, preset("tiny")
    except Exception as exc:           # the generator is being written by another worker
        from tests.conftest import SHARED_DATA

        pair = SHARED_DATA / "reunion_pair"
        if not pair.is_dir():
            pytest.skip(f"no synthetic site ({exc}) and no shared data")
        return pair, preset("default").with_overrides({"tiling.tile_size": 400})


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """A viewer reconstructing a small site live, with a log of what it displayed."""
    from aerec_viewer.app import ViewerApp

    root = tmp_path_factory.mktemp("viewer")
    site, cfg = _small_site(root)
    out = root / "out"
    app = ViewerApp(out, site, cfg, mode="run", port=0, update_hz=10.0, until="sparse")
    events: list = []
    real = app.worker.handle
    app.worker.handle = lambda ev: (events.append((type(ev).__name__, time.time(), ev)), real(ev))[1]
    trace = []
    app.start()

    def sample():
        s = app.worker.snapshot()
        trace.append((s.status, sum(len(g.tiles) for g in s.groups.values()),
                      app.scene.displayed_points(), s.stage, s.stage_done, s.stage_total))

    t0 = time.time()
    while not app.worker.done.wait(0.1) and time.time() - t0 < 240:
        sample()
    assert app.worker.done.is_set(), "the live run did not finish in 240 s"
    # the loop above samples while the run goes on; the last row must be the display once the
    # worker's final state has been applied, not whatever the last sample caught (a race)
    app.wait_idle()
    sample()
    # the image plane's texture is read on a thread and placed by a later tick: wait for it, or
    # a test that runs first (alone, with -k) finds no plane
    t1 = time.time()
    while app.pick_plane is None and time.time() - t1 < 30:
        time.sleep(0.05)
        app.wait_idle()
    app.gcp_panel.zoom_click.value = False      # one click places (the loupe has its own test)
    yield app, events, trace, out, site, cfg
    app.stop()


def test_live_run_grows_points_and_tiles_to_the_end(live):
    app, events, trace, out, site, cfg = live
    snap = app.worker.snapshot()
    assert snap.status == "done", snap.error
    g0 = snap.groups[0]
    # tiles appear one by one; every registered tile has an outline node, the newest is marked
    tiles = [t for _, t, *_ in trace]
    assert tiles == sorted(tiles) and tiles[-1] == len(g0.tiles) > 2
    assert len(g0.tiles) == g0.total_tiles or len(g0.tiles) > 0.8 * g0.total_tiles
    assert all((0, tid) in app.scene._tiles for tid in g0.tiles)
    assert 0 in app.scene._newest_nodes
    # points grow monotonically within a generation (a ModelUpdated may drop rejected outliers)
    n, gen_sizes = 0, []
    for name, _, ev in events:
        if name == "PointsAdded" and ev.kind == "sparse":
            n += len(ev.ids)
            gen_sizes.append(n)
        elif name == "ModelUpdated":
            assert len(ev.ids) >= 0.8 * n
            n = len(ev.ids)
    shown = [row[2] for row in trace]
    assert shown[-1] == app.scene.displayed_points() == g0.sparse.n
    assert max(shown) <= g0.sparse.n * 1.25 and shown.count(0) < len(shown)
    # the scene holds float32 chunks at stable paths
    st = app.scene._clouds[(0, "sparse")]
    assert st.chunks and all(c.handle.name.startswith("/recon/g0/sparse/chunk_") for c in st.chunks)
    assert all(c.xyz.dtype == np.float32 for c in st.chunks)
    assert np.abs(np.concatenate([c.xyz for c in st.chunks])).max() < 1e5   # local origin
    # progress reached the end: bar full, sfm stage counted every registered tile
    assert app.g_progress.value == 100.0
    assert "finished" in app.g_status.content
    assert f"{len(g0.tiles)} / {g0.total_tiles}" in app.g_stats.content
    assert "affine frame" in app.g_frame.content


def test_tiles_are_textured_until_the_dense_cloud_covers_them(live):
    """`auto` (the default): a sparse-only run shows each tile's image; a group with dense points
    shown draws outlines (textured tiles are most of the drawing cost without a GPU)."""
    app = live[0]
    sc = app.scene
    assert sc.settings.tiles == "auto"
    assert sc._tiles and all(node.image is not None for node in sc._tiles.values())
    assert sc.tile_mode(dense=False) == "textured" and sc.tile_mode(dense=True) == "outlines"
    sc.settings.show_dense = False
    try:
        assert sc.tile_mode(dense=True) == "textured"
    finally:
        sc.settings.show_dense = True
    sc.settings.tiles = "textured"
    try:
        assert sc.tile_mode(dense=True) == "textured"
    finally:
        sc.settings.tiles = "auto"


def test_display_controls_apply_to_the_scene(live):
    app = live[0]
    st = app.scene._clouds[(0, "sparse")]
    before = st.chunks[0].handle.point_size
    app.call(lambda: (setattr(app.scene.settings, "point_size", 2.0), app.scene.apply_point_size()))
    assert np.isclose(st.chunks[0].handle.point_size, 2 * before)
    for mode in dp.COLOR_MODES:
        app.call(lambda: (setattr(app.scene.settings, "color_mode", mode), app.scene.apply_colors()))
    n_all = app.scene.displayed_points()
    app.call(lambda: (setattr(app.scene.settings, "budget", max(10, n_all // 4)), app._force()))
    app.wait_idle()
    assert app.scene.displayed_points() < 0.5 * n_all
    app.call(lambda: (setattr(app.scene.settings, "budget", 150_000), app._force()))
    app.wait_idle()
    assert app.scene.displayed_points() == n_all


def _ray_to(app, col, row):
    p = app.pick_plane
    target = p.point_of(col, row)
    origin = target + np.array([3.0, -4.0, 40.0]) * p.render_width / 40.0
    return origin, target - origin


def test_gcp_picks_through_the_click_handlers_then_upgrade(live):
    app, events, trace, out, site, cfg = live
    assert app.pick_plane is not None
    img = app.pick_plane.window.image
    # a new GCP from typed coordinates, then a click on the image plane observes it
    gp = app.gcp_panel
    app.call(lambda: gp.select_id(None))
    app.wait_idle()                      # the list's change is applied (it clears the fields)
    app.call(lambda: (setattr(gp.gid, "value", "NEW-1"),
                      setattr(gp.x, "value", 55.65), setattr(gp.y, "value", -21.23),
                      setattr(gp.h, "value", 2300.0)))
    o, d = _ray_to(app, 123.25, 200.75)
    pix = app.call(lambda: app.on_plane_click(o, d))
    assert pix is not None and abs(pix[0] - 123.25) < 1e-3 and abs(pix[1] - 200.75) < 1e-3
    assert app.last_click[:2] == ("NEW-1", img)
    n_img = len(app.call(gp._registered_images))
    assert f"| **NEW-1** | control | 1 / {n_img} | - |" in gp.listing.content      # the working set's table
    saved = json.loads((out / "gcps.geojson").read_text())
    feat = {f["properties"]["id"]: f for f in saved["features"]}["NEW-1"]
    assert np.allclose(feat["properties"]["observations"][img], [123.25, 200.75], atol=1e-3)
    # a second click on the same GCP replaces its observation in that image
    o, d = _ray_to(app, 130.0, 190.0)
    app.call(lambda: app.on_plane_click(o, d))
    assert np.allclose(app.session.get("NEW-1").observations[img], (130.0, 190.0), atol=1e-3)
    # the cloud pick: a ray through a displayed point sets the GCP's affine position
    ch = app.scene._clouds[(0, "sparse")].chunks[0]
    target = ch.xyz[5].astype(float)
    app.call(app.arm_cloud_pick)
    xyz = app.call(lambda: app.on_cloud_click("NEW-1", target + [0, 0, 50.0], [0, 0, -1.0]))
    T = app.scene._clouds[(0, "sparse")].transform
    assert np.allclose(T.apply(xyz[None])[0], target, atol=1e-2)
    assert app._armed is None and 0 in app.session.get("NEW-1").affine_picked
    # markers: on the plane for observations in this image, on the cloud for placed GCPs
    app.wait_idle()
    names = set(app._marks)
    assert "/gcp/plane_marks/NEW-1" in names and "/gcp/cloud/g0/NEW-1" in names
    # markers are rings that keep their size on screen: zooming in 4x shrinks them 4x in the
    # world (the view that moved last sets it)
    from types import SimpleNamespace

    def view(d):
        return SimpleNamespace(client=SimpleNamespace(client_id=99), position=np.array([0.0, 0.0, d]),
                               wxyz=np.array([1.0, 0.0, 0.0, d]), look_at=np.zeros(3), fov=0.8,
                               image_height=900)

    app._camera_update(view(400.0))
    app.wait_idle()
    r_far = app._marks["/gcp/plane_marks/NEW-1"].radius
    app._camera_update(view(100.0))
    app.wait_idle()
    r_near = app._marks["/gcp/plane_marks/NEW-1"].radius
    assert r_far / r_near == pytest.approx(4.0, rel=1e-6)
    assert r_near == pytest.approx(MARK_RING_PX * 2 * 100.0 * np.tan(0.4) / 900)
    app.call(lambda: delete_gcp(app.session, "NEW-1"))
    app.call(lambda: app.gcps_changed(select=None))
    assert "NEW-1" not in app.session.ids

    # the upgrade with the site's GCPs (copied into the working set on first opening)
    assert not app.g_upgrade.disabled, app.g_ready.content
    outcome = app.call(app.do_upgrade)
    assert outcome.ok and app.frame == "euclidean"
    res = outcome.results[0].to_dict()
    checks = [p for p in res["points"] if p["status"] == "check"]
    assert checks and res["stats"]["check"]["n"] == len(checks)
    assert res["stats"]["check"]["rmse_3d_m"] < 5.0
    md = app.g_upgrade_md.content
    assert "| GCP | role | status | dE m | dN m | dU m | reproj px |" in md and "check" in md
    assert "N = 4" in md or "LOO" in md.upper() or "loo" in md
    # the metric bend step: said when applied (the 3D view places the clouds by H_A alone)
    applied = outcome.metric[0].get("applied")
    assert ("Metric bend step: a horizontal warp of" in md) == bool(applied)
    assert not (out / "viewer_upgrade.json").exists()      # one upgrade record: the pipeline's
    assert "stops after the sparse stage" in app.worker.rerun_from("upgrade")   # --until sparse
    app.wait_idle()
    st = app.scene._clouds[(0, "sparse")]
    assert st.transform.kind == "euclidean" and "Euclidean frame" in app.g_frame.content
    # metres, z up: the ENU cloud spans a plausible site and its heights are metric
    P = np.concatenate([c.xyz for c in st.chunks]).astype(float)
    assert 20.0 < np.ptp(P[:, 0]) < 20_000.0 and np.ptp(P[:, 2]) < np.ptp(P[:, 0])
    app.call(lambda: app.set_frame("affine"))
    assert app.scene._clouds[(0, "sparse")].transform.kind == "affine"


def test_loupe_texture_enlarges_pixels_and_leaves_the_aimed_pixel_clear():
    from aerec_viewer.app import LOUPE_CROSS, loupe_texture, loupe_window

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


def test_loupe_first_click_zooms_second_click_places(live):
    """With "Click zooms in first": a click on the whole image opens the loupe there (nothing
    recorded, the plane shows 40 x 40 full-resolution pixels losslessly), a click in the loupe is
    the observation, to the same sub-pixel precision, and the plane goes back to the region."""
    from aerec_viewer.app import LOUPE_PX

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    gid = app.session.ids[0]
    app.call(lambda: gp.refresh(select=gid))
    app.call(lambda: setattr(gp.zoom_click, "value", True))
    try:
        if app.pick_plane is None:
            app.call(lambda: app.show_image_plane(wait=True))
        whole = app.pick_plane.window
        img = whole.image
        before = dict(app.session.get(gid).observations)
        o, d = _ray_to(app, 150.4, 160.6)
        assert app.call(lambda: app.on_plane_click(o, d)) is None
        assert app.session.get(gid).observations == before              # nothing recorded
        win = app.pick_plane.window
        assert app.loupe is not None and win == app.loupe[0] and win.image == img
        assert (win.width, win.height) == (LOUPE_PX, LOUPE_PX) and win.contains([(150.4, 160.6)])[0]
        assert not gp.leave_loupe.disabled
        o, d = _ray_to(app, 152.37, 158.81)
        pix = app.call(lambda: app.on_plane_click(o, d))
        assert pix is not None and abs(pix[0] - 152.37) < 1e-3 and abs(pix[1] - 158.81) < 1e-3
        assert np.allclose(app.session.get(gid).observations[img], (152.37, 158.81), atol=1e-3)
        assert app.loupe is None and app.pick_plane.window == whole and gp.leave_loupe.disabled
        # Leave the loupe records nothing
        o, d = _ray_to(app, 300.0, 100.0)
        app.call(lambda: app.on_plane_click(o, d))
        assert app.loupe is not None
        app.call(app.close_loupe)
        assert app.loupe is None and app.pick_plane.window == whole
        assert np.allclose(app.session.get(gid).observations[img], (152.37, 158.81), atol=1e-3)
    finally:
        app.call(lambda: undo(app.session))
        app.call(lambda: app.gcps_changed(select=gid))
        app.call(lambda: setattr(gp.zoom_click, "value", False))


def test_a_click_in_the_loupe_walks_on_to_the_gcps_next_image(live):
    """With "Then its next image": after a click in the loupe records an observation, the next
    image without one opens in the loupe at the GCP's prediction (close to its true pixel);
    Enter there records it and walks on; once every image has one, the plane stays."""
    app, events, trace, out, site, cfg = live
    if not (site / "truth" / "gcps_truth.json").exists():
        pytest.skip("needs the synthetic site's truth")
    gp = app.gcp_panel
    truth = {g["id"]: {k: tuple(v) for k, v in g["true_observations"].items()} for g in _truth_gcps(site)}
    model = app.models[0]
    gid = next(g for g in app.session.ids if g in truth
               and sum(im in model.images for im in truth[g]) >= 3)
    tob = {k: v for k, v in truth[gid].items() if k in model.images}
    saved = dict(app.session.get(gid).observations)
    app.call(lambda: gp.refresh(select=gid))
    for im in list(saved):
        app.call(lambda im=im: remove_observation(app.session, gid, im))
    first = sorted(tob)[0]

    def predict_now(image):
        from recon_core.euclidean.gcp_transfer import predict_observation

        return predict_observation(model, {im.name: im for im in app.site.images},
                                   app.session.get(gid).observations, image)
    app.call(lambda: setattr(gp.image, "value", first))
    app.call(lambda: setattr(gp.zoom_click, "value", True))
    try:
        app.call(lambda: app.show_image_plane(wait=True))
        o, d = _ray_to(app, *tob[first])
        app.call(lambda: app.on_plane_click(o, d))                     # opens the loupe
        o, d = _ray_to(app, *tob[first])
        app.call(lambda: app.on_plane_click(o, d))                     # records, walks on
        app.wait_idle()
        nxt = gp.image.value
        assert nxt != first and nxt in tob and app.loupe is not None and app.loupe[0].image == nxt
        assert np.hypot(*(np.asarray(app.loupe[1]) - tob[nxt])) < 3.0, (app.loupe[1], tob[nxt])
        assert gp.prediction is not None and gp.prediction[1].image == nxt
        # an offer made stale before it is shown (the operator pressed Undo meanwhile) is dropped
        app.call(app.close_loupe)
        app.call(gp.drop_prediction)
        pred = gp.prediction
        app.call(lambda: gp.show_hint(gid, predict_now(nxt), None) or undo(app.session))
        app.wait_idle()
        assert gp.prediction is None and app.loupe is None
        app.call(lambda: redo(app.session))
        app.call(lambda: gp.show_hint(gid, predict_now(nxt), None))
        app.wait_idle()
        assert gp.prediction is not None and app.loupe is not None and pred is None
        for _ in range(len(tob) - 1):                                   # Enter on each in turn
            app.call(gp._accept)
            app.wait_idle()
        obs = app.session.get(gid).observations
        assert set(obs) == set(tob)
        assert app.loupe is None and "N for the next GCP" in gp.status.content
        err = [np.hypot(obs[k][0] - tob[k][0], obs[k][1] - tob[k][1]) for k in tob if k != first]
        assert max(err) < 1.5, err
    finally:
        app.call(app.close_loupe)
        for im in list(app.session.get(gid).observations):
            app.call(lambda im=im: remove_observation(app.session, gid, im))
        for im, xy in saved.items():
            app.call(lambda im=im, xy=xy: add_observation(app.session, gid, im, *xy))
        app.call(lambda: setattr(gp.zoom_click, "value", False))
        app.call(lambda: app.gcps_changed(select=gid))


def test_go_to_an_observation_opens_it_in_the_loupe_and_flags_a_large_residual(live):
    """The GCP's description gives each observation's reprojection residual and flags one above
    1 px; "Go to its observation" shows it in the loupe, where a click moves it."""
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    model = app.models[0]
    gid = next(g.id for g in app.session.gcps
               if sum(im in model.images for im in g.observations) >= 3)
    obs = dict(app.session.get(gid).observations)
    im = sorted(obs)[1]
    app.call(lambda: gp.refresh(select=gid))
    assert "residual" in gp.info.content and "check it" not in gp.info.content, gp.info.content
    assert set(gp.jump.options) == {gp.JUMP_NONE, *obs}
    c, r = obs[im]
    app.call(lambda: add_observation(app.session, gid, im, c + 6.0, r))     # a misclick
    app.call(lambda: app.gcps_changed(select=gid))
    line = next(ln for ln in gp.info.content.splitlines() if ln.startswith(f"- {im}"))
    assert "check it" in line, gp.info.content
    try:
        app.call(lambda: setattr(gp.jump, "value", im))
        app.wait_idle()
        assert gp.jump.value == gp.JUMP_NONE and gp.image.value == im
        assert app.loupe is not None and app.loupe[0].image == im
        assert np.allclose(app.loupe[1], (c + 6.0, r))
    finally:
        app.call(app.close_loupe)
        app.call(lambda: undo(app.session))
        app.call(lambda: app.gcps_changed(select=gid))
    assert app.session.get(gid).observations[im] == obs[im]


def test_next_gcp_passes_over_finished_gcps(live):
    """N goes to a GCP that still has images to place while there is one; every GCP finished,
    it walks them all; the note names the selection (not the previous GCP's state)."""
    app = live[0]
    gp = app.gcp_panel
    ids = app.session.ids
    assert len(ids) >= 3
    finished = [g for g in ids if app.call(lambda g=g: gp.finished(g))]
    if len(finished) < 2:
        pytest.skip("the live site has fewer than 2 GCPs observed in every image")
    # one finished GCP made unfinished (an observation removed, undone after)
    target = finished[-1]
    im = sorted(app.session.get(target).observations)[0]
    app.call(lambda: remove_observation(app.session, target, im))
    try:
        app.call(lambda: gp.refresh(select=finished[0]))
        todo = [g for g in ids if not app.call(lambda g=g: gp.finished(g))]
        assert target in todo
        k0 = ids.index(finished[0])
        between = [ids[(k0 + j) % len(ids)] for j in range(1, len(ids))]
        first = app.call(lambda: gp.step_gcp(+1))
        assert first in todo
        app.wait_idle()                          # the selection's own callbacks have run
        status = app.gcp_panel.status.content
        assert status.startswith(f"{first} selected"), status
        n_over = between.index(first)             # the finished ones between the two
        assert (f"; {n_over} finished GCP(s) passed over" in status) == (n_over > 0), status
        if len(todo) >= 2:                      # they alternate, the finished ones passed over
            seen = [app.call(lambda: gp.step_gcp(+1)) for _ in range(len(todo))]
            assert set(seen) == set(todo)
    finally:
        app.call(lambda: undo(app.session))
        app.call(lambda: app.gcps_changed(select=target))
    # all finished again: N walks every GCP
    if all(app.call(lambda g=g: gp.finished(g)) for g in ids):
        app.call(lambda: gp.refresh(select=ids[-1]))
        assert app.call(lambda: gp.step_gcp(+1)) == ids[0]


def test_next_previous_gcp_and_place_it_in_its_other_images(live):
    """Next / Previous walk the working set (wrapping); "Place it in its other images" records
    the confirmed predictions of a GCP observed once, in one undo step, close to where the site's
    own clicks put it."""
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    ids = app.session.ids
    app.call(lambda: gp.refresh(select=ids[-1]))
    todo = [g for g in ids if not app.call(lambda g=g: gp.finished(g))]

    def expect(cur, step):            # cyclic, over the unfinished ones while there is another
        pool = todo if set(todo) - {cur} else ids
        k = ids.index(cur)
        return next(ids[(k + step * j) % len(ids)] for j in range(1, len(ids) + 1)
                    if ids[(k + step * j) % len(ids)] in pool)
    nxt = expect(ids[-1], +1)
    assert app.call(lambda: gp.step_gcp(+1)) == nxt and gp.selected() == nxt
    assert app.call(lambda: gp.step_gcp(-1)) == expect(nxt, -1)
    cat = {c.id: c for c in app.session.catalogue}
    model = app.models[0]
    gid = next(g.id for g in app.session.gcps if g.id in cat and len(cat[g.id].observations) >= 3
               and all(im in model.images for im in cat[g.id].observations))
    site_obs = dict(cat[gid].observations)
    keep = sorted(site_obs)[0]
    app.call(lambda: gp.refresh(select=gid))
    for im in list(app.session.get(gid).observations):
        if im != keep:
            app.call(lambda im=im: remove_observation(app.session, gid, im))
    app.call(lambda: add_observation(app.session, gid, keep, *site_obs[keep]))
    n_undo = len(app.session._undo)
    result = app.call(gp._place_all)
    placed = [im for im, v in result.items() if v == "placed"]
    assert placed, result
    assert len(app.session._undo) == n_undo + 1                    # one step
    for im in placed:
        c, r = app.session.get(gid).observations[im]
        assert np.hypot(c - site_obs[im][0], r - site_obs[im][1]) < 3.0, (im, (c, r), site_obs[im])
    app.call(lambda: undo(app.session))
    assert set(app.session.get(gid).observations) == {keep}
    for im, xy in site_obs.items():                                 # as the site has it
        app.call(lambda im=im, xy=xy: add_observation(app.session, gid, im, *xy))
    app.call(lambda: app.gcps_changed(select=gid))


def test_an_image_left_by_place_all_opens_in_the_loupe_and_enter_accepts(live, monkeypatch):
    """When "Place it in its other images" leaves an image to the operator with a prediction,
    the plane switches to that image and the loupe opens at the predicted pixel; accepting
    records exactly that pixel there; nothing else was recorded."""
    from aerec_viewer import gcp_panel as gpm
    from recon_core.euclidean.gcp_transfer import Prediction

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    gid = next(g.id for g in app.session.gcps if g.observations)
    app.call(lambda: gp.refresh(select=gid))
    target = next(im for im in app.models[0].images if im != gp.image.value)
    had = app.session.get(gid).observations.get(target)
    if had is not None:
        app.call(lambda: remove_observation(app.session, gid, target))
    hint = Prediction(target, 201.25, 143.5, (201.25, 143.5), None, "from one observation")
    monkeypatch.setattr(gpm, "place_in_other_images",
                        lambda model, images, seen, **kw: ({}, {target: "not confirmed"}, {target: hint}))
    try:
        before = {k: dict(g.observations) for k, g in ((g.id, g) for g in app.session.gcps)}
        result = app.call(lambda: gp._place_all())
        app.wait_idle()
        assert result == {target: "not confirmed"}
        assert {g.id: dict(g.observations) for g in app.session.gcps} == before
        assert gp.image.value == target and app.pick_plane.window.image == target
        assert app.loupe is not None and app.loupe[0].image == target
        assert np.allclose(app.loupe[1], (201.25, 143.5)) and app.loupe[0].contains([(201.25, 143.5)])[0]
        assert gp.prediction is not None and not gp.accept.disabled
        app.call(gp._accept)
        assert app.session.get(gid).observations[target] == (201.25, 143.5)
    finally:
        app.call(app.close_loupe)
        app.call(lambda: undo(app.session))
        if had is not None:
            app.call(lambda: add_observation(app.session, gid, target, *had))
        app.call(lambda: app.gcps_changed(select=gid))


def test_role_and_enable_toggles_are_saved_undoable_and_drive_readiness(live):
    """"Make it a check point" and "Disable it" flip the selected GCP, say so on their labels,
    reach the working file ("enabled": false) and the readiness the Upgrade button counts, and
    Undo reverts each."""
    from aerec_viewer.results import gcp_readiness

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    gid = next(g.id for g in app.session.gcps if g.role == "control")
    app.call(lambda: gp.refresh(select=gid))
    assert gp.role_toggle.label == "Make it a check point" and gp.enable_toggle.label == "Disable it"
    app.call(gp._toggle_role)
    assert app.session.get(gid).role == "check" and gp.role_toggle.label == "Make it a control point"
    app.call(gp._toggle_enabled)
    assert not app.session.get(gid).enabled and gp.enable_toggle.label == "Enable it"
    assert gcp_readiness(app.session, app.models)[gid] == (False, "disabled")
    saved = {f["properties"]["id"]: f["properties"] for f in json.loads(app.session.path.read_text())["features"]}
    assert saved[gid]["enabled"] is False and saved[gid]["role"] == "check"
    app.call(gp._undo)
    assert app.session.get(gid).enabled and gp.enable_toggle.label == "Disable it"
    app.call(gp._undo)
    assert app.session.get(gid).role == "control"
    saved = {f["properties"]["id"]: f["properties"] for f in json.loads(app.session.path.read_text())["features"]}
    assert "enabled" not in saved[gid] and saved[gid]["role"] == "control"


def test_a_click_never_lands_on_the_gcp_another_tab_chose(live):
    """The GCP list is shared by the tabs: tab A chooses one GCP, tab B then another; A's next
    click records nothing (and says which GCP is now chosen) instead of observing B's GCP; its
    click after that, and B's clicks, go through."""
    from types import SimpleNamespace

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    a, b = SimpleNamespace(client_id=9001), SimpleNamespace(client_id=9002)
    ids = app.session.ids
    g1 = ids[0]
    before_all = {g: dict(app.session.get(g).observations) for g in ids}
    app.call(lambda: gp.refresh(select=g1))
    app.call(lambda: gp.note_choice(a))                        # A chose g1 in the list
    g2 = app.call(lambda: gp.step_gcp(+1, b))                  # B pressed N: g2 for everyone
    assert gp.selected() == g2 != g1
    before = {g: before_all[g] for g in (g1, g2)}
    if app.pick_plane is None:
        app.call(lambda: app.show_image_plane(wait=True))
    o, d = _ray_to(app, 120.0, 130.0)
    with pytest.raises(GcpError, match=f"another tab changed the GCP to {g2}"):
        app.call(lambda: app.on_plane_click(o, d, a))
    assert {g: dict(app.session.get(g).observations) for g in (g1, g2)} == before
    n_undo = len(app.session._undo)
    try:
        assert app.call(lambda: app.on_plane_click(o, d, b)) is not None          # B: its own GCP
        assert app.call(lambda: app.on_plane_click(o, d, a)) is not None          # A, warned: goes through
        assert len(app.session._undo) == n_undo + 2
        # one tab's own actions that change the list on the server (Create, Delete, Undo, a
        # selection made for it) never refuse its click
        app.call(lambda: gp.refresh(select=g1))
        assert app.call(lambda: app.on_plane_click(o, d, b)) is not None
        assert len(app.session._undo) == n_undo + 3
    finally:
        for _ in range(len(app.session._undo) - n_undo):
            app.call(lambda: undo(app.session))
        app.call(lambda: app.gcps_changed(select=g1))
    assert {g: dict(app.session.get(g).observations) for g in (g1, g2)} == before


def test_gcp_panel_is_safe_to_edit(live):
    """The operator's safety nets in the GCP tab: choosing "(new GCP ...)" empties the ground
    fields, so a click cannot create a control GCP at the previous GCP's coordinates; Delete asks
    for confirmation; a cloud pick can be forgotten; Undo reverts the last edit."""
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    first = app.session.ids[0]
    app.call(lambda: gp.refresh(select=first))
    assert gp.x.value != 0.0
    app.call(lambda: gp.refresh(select=None))              # "(new GCP from the fields below)"
    assert (gp.x.value, gp.y.value, gp.h.value, gp.gid.value) == (0.0, 0.0, 0.0, "")
    n = len(app.session.ids)
    o, d = _ray_to(app, 100.0, 100.0)
    with pytest.raises(GcpError):
        app.call(lambda: app.on_plane_click(o, d))
    assert len(app.session.ids) == n                         # nothing created
    # delete: the first press only asks, the second deletes, Undo restores
    app.call(lambda: gp.refresh(select=first))
    obs = dict(app.session.get(first).observations)
    app.call(gp._delete)
    assert first in app.session.ids and gp.delete.label.startswith("Confirm: delete " + first)
    app.call(gp._delete)
    assert first not in app.session.ids and gp.delete.label == "Delete the selected GCP"
    assert gp.undo.label == f"Undo: delete {first}" and not gp.undo.disabled
    app.call(gp._undo)
    assert first in app.session.ids and app.session.get(first).observations == obs
    assert gp.redo.label == f"Redo: delete {first}"
    # a cloud pick overrides the image observations until it is forgotten
    app.call(lambda: gp.refresh(select=first))
    app.call(lambda: set_affine_position(app.session, first, 0, np.array([1.0, 2.0, 3.0])))
    app.call(gp._forget_pick)
    assert not app.session.get(first).affine_picked
    with pytest.raises(GcpError):
        app.call(gp._forget_pick)


def test_upgrade_with_too_few_gcps_explains_itself(live, tmp_path):
    from aerec_viewer.gcp_session import GcpSession, save
    from aerec_viewer.results import run_upgrade
    from recon_core.errors import ReconstructionError

    app = live[0]
    s = GcpSession(tmp_path / "g.geojson", dict(app.session.images), gcps=app.session.gcps[:3])
    save(s)
    with pytest.raises(ReconstructionError, match="need >= 4|4"):
        run_upgrade(s, app.models, app.cfg)


def test_dsm_and_height_error_panel(live):
    """With OUT/dsm.tif (here: the site's GT DSM itself) the panel shows the DSM, evaluates it
    against gt_dsm.tif, shows the error map and its figures, and drapes it in the scene."""
    import shutil

    from aerec_viewer.results import evaluate_now, find_dsm_products

    app, events, trace, out, site, cfg = live
    if app.site.gt_dsm is None:
        pytest.skip("this site has no gt_dsm.tif")
    shutil.copy(app.site.gt_dsm, out / "dsm.tif")
    dp_ = app.dsm_panel
    app.call(lambda: dp_.refresh(None, force=True))
    assert dp_.dsm_img.visible and dp_.evaluate.visible
    evaluate_now(out, app.site.gt_dsm)
    p = find_dsm_products(out)
    assert p.eval_json and p.error_png and p.error_tif
    app.call(lambda: dp_.refresh(None, force=True))
    assert dp_.err_img.visible and "median abs. height error" in dp_.md.content
    assert "completeness" in dp_.md.content and not dp_.evaluate.visible
    if app.upgrade is None:
        app.call(app.do_upgrade)
    app.call(lambda: app.set_frame("euclidean"))
    app.call(lambda: setattr(dp_.drape, "value", True))
    assert app.call(dp_.show_drape) and dp_.drape_handle is not None
    top = app.scene_bounds()[1][2]
    assert float(dp_.drape_handle.position[2]) > top            # above the cloud, not hidden by it
    assert "Written 20" in dp_.md.content and "GCPs: " in dp_.md.content   # provenance
    app.call(lambda: setattr(dp_.drape, "value", False))
    app.call(dp_.show_drape)
    assert dp_.drape_handle is None


def test_reopen_restores_gcps_without_recomputing(live):
    from aerec_viewer.app import ViewerApp

    app, events, trace, out, site, cfg = live
    app.call(lambda: add_observation(app.session, app.session.ids[0], app.session.gcps[0].observations
                                     and next(iter(app.session.gcps[0].observations)) or
                                     sorted(app.session.images)[0], 10.5, 11.5))
    stamps = {p: p.stat().st_mtime for p in (out / "stages").glob("*.json")}
    re = ViewerApp(out, mode="reopen", port=0, update_hz=10.0).start()
    try:
        assert re.worker.join(60)
        re.wait_idle()
        snap = re.worker.snapshot()
        assert snap.status == "reopened", snap.error
        assert snap.groups[0].sparse.n == app.worker.snapshot().groups[0].sparse.n
        assert re.scene.displayed_points() == snap.groups[0].sparse.n
        assert re.session.ids == app.session.ids
        first = re.session.gcps[0]
        assert any(np.allclose(v, (10.5, 11.5)) for v in first.observations.values())
        assert {p: p.stat().st_mtime for p in (out / "stages").glob("*.json")} == stamps
        assert re.port != app.port
    finally:
        re.stop()


def test_run_on_a_finished_out_shows_the_saved_cloud_without_recomputing(live):
    from aerec_viewer.app import ViewerApp

    app, events, trace, out, site, cfg = live
    stamps = {p: p.stat().st_mtime for p in (out / "stages").glob("*.json")}
    again = ViewerApp(out, site, cfg, mode="run", port=0, update_hz=10.0, until="sparse").start()
    try:
        assert again.worker.join(60)
        again.wait_idle()
        snap = again.worker.snapshot()
        assert snap.status == "done", snap.error
        assert snap.groups[0].sparse.n == app.worker.snapshot().groups[0].sparse.n
        assert again.scene.displayed_points() == snap.groups[0].sparse.n and again.models
        assert {p: p.stat().st_mtime for p in (out / "stages").glob("*.json")} == stamps
    finally:
        again.stop()


def test_cli_resolves_sites_outputs_and_the_demo(tmp_path, small_site, monkeypatch):
    import argparse

    from aerec_viewer import cli

    monkeypatch.setenv("AEREC_CACHE", str(tmp_path / "cache"))
    mode, site, out = cli.resolve_target(small_site, None, None)
    assert mode == "run" and site == small_site and out.name == "site_aerec_out"
    (tmp_path / "o" / "affine").mkdir(parents=True)
    assert cli.resolve_target(tmp_path / "o", None, None)[0] == "reopen"
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="command")
    cli.register(sub)
    a = p.parse_args(["view", str(small_site), "--port", "0", "--host", "127.0.0.1"])
    assert a.func is cli.cmd_view and a.port == 0 and a.target == small_site
    assert p.parse_args(["view"]).target is None


def test_viewer_upgrade_equals_aerec_run_redo_from_upgrade(tiny_run, tmp_path):
    """One upgrade path: the Upgrade button (on an operator's working set with changed roles and
    a position picked on the cloud) and `aerec run --redo-from upgrade` on a copy of the same OUT
    give the identical H_A and a byte-identical dsm.tif; the pick is honoured by both."""
    import json
    import shutil

    from aerec_viewer.app import ViewerApp
    from recon_core.cli import main as aerec
    from recon_core.euclidean.georef import triangulate_gcp
    from recon_core.io.gcps import read_gcps_geojson, write_gcps_geojson
    from recon_core.io.layout import OutLayout

    state, _ = tiny_run
    a, b = tmp_path / "viewer_out", tmp_path / "cli_out"
    shutil.copytree(state.out, a)
    gcps = read_gcps_geojson(state.site.root / "gcps.geojson")
    ctrl = [g for g in gcps if g.role == "control"]
    check = [g for g in gcps if g.role == "check"]
    check[0].role = "control"                                  # a fifth control point ...
    picked = check[1]
    picked.role = "control"                                    # ... and a sixth, picked on the cloud
    X = triangulate_gcp(state.models[0], picked.observations).xyz
    assert X is not None and len(ctrl) == 4
    picked.affine_picked[0] = X + 0.05 * np.ptp(state.models[0].X[state.models[0].has_point], axis=0)
    write_gcps_geojson(OutLayout(a).gcps, gcps)
    shutil.copytree(a, b)

    app = ViewerApp(a, state.site.root, None, mode="reopen", port=0, update_hz=20.0)
    app.start()
    try:
        assert app.worker.done.wait(60) and app.worker.snapshot().status == "reopened"
        app.wait_idle()
        outcome = app.call(app.do_upgrade)
        deadline = time.time() + 120
        while not (app.worker.done.is_set() and app.worker.redo_from == "upgrade"):
            assert time.time() < deadline, "the viewer's DSM re-run did not start and finish"
            time.sleep(0.1)
        assert app.worker.snapshot().status == "done", app.worker.snapshot().error
    finally:
        app.stop()
    assert aerec(["run", str(state.site.root), "--out", str(b), "--preset", "tiny",
                  "--redo-from", "upgrade", "--quiet"]) in (0, None)

    rec_a = json.loads(OutLayout(a).upgrade_record(0).read_text())
    rec_b = json.loads(OutLayout(b).upgrade_record(0).read_text())
    assert rec_a["H"] == rec_b["H"]
    assert np.array_equal(np.array(rec_a["H"]), outcome.results[0].H)        # what the viewer showed
    assert rec_a["gcp_affine"][picked.id]["source"] == "picked"
    before = json.loads(OutLayout(state.out).upgrade_record(0).read_text())["H"]
    assert not np.allclose(before, rec_a["H"])                                  # the edits mattered
    assert OutLayout(a).dsm.read_bytes() == OutLayout(b).dsm.read_bytes()
    assert not (a / "viewer_upgrade.json").exists()
    # a viewer whose configuration no longer matches the saved sparse model refuses to re-run
    # (it would recompute the model and move the affine frame under the picked positions)
    from recon_core.config import preset
    w = ReconWorker(state.site.root, a, preset("tiny").with_overrides({"tiling.tile_size": 250}),
                    mode="reopen")
    w.done.set()
    assert "does not match this configuration" in w.rerun_from("upgrade")


def test_a_failed_stage_is_named_with_a_hint_and_the_results_tab_says_so(tiny_run, tmp_path,
                                                                          monkeypatch):
    """A crash at the very start of the DSM stage (before it reports any progress, as an ICP
    library failing to load would): the status names the DSM stage, not the last stage that
    reported progress, gives a one-line hint, and the Results tab says there is no DSM because
    that stage failed instead of asking to wait."""
    import shutil

    from aerec_viewer.results import no_dsm_markdown
    from recon_core import pipeline
    from recon_core.config import preset
    from recon_core.io.layout import OutLayout

    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    lay = OutLayout(out)
    lay.stage_record("dsm").unlink()
    lay.dsm.unlink()

    def broken(state, bus):
        raise ImportError("libusb-1.0.so.0: cannot open shared object file")

    monkeypatch.setattr(pipeline.STAGE_MODULES["dsm"], "run", broken)
    w = ReconWorker(state.site.root, out, preset("tiny"), mode="run", until="dsm").start()
    assert w.join(120)
    snap = w.snapshot()
    assert snap.status == "failed" and snap.failed_stage == "dsm", (snap.status, snap.failed_stage)
    assert "libusb" in snap.error and "pip install" in snap.hint
    md = no_dsm_markdown(snap)
    assert "dsm stage failed" in md and "libusb" in md and "appears here" not in md
    assert "appears here" in no_dsm_markdown(None)


def test_the_dsm_says_which_gcp_set_and_upgrade_it_comes_from(tiny_run, tmp_path):
    import os
    import shutil

    from aerec_viewer.results import provenance_markdown
    from recon_core.io.layout import OutLayout

    state, _ = tiny_run
    out = tmp_path / "out"
    shutil.copytree(state.out, out)
    lay = OutLayout(out)
    md = provenance_markdown(out)
    assert "Written 20" in md and "UTC" in md
    rec = json.loads(lay.upgrade_record(0).read_text())
    used = [p["id"] for p in rec["points"] if p["role"] == "control" and p["status"] == "used"]
    assert len(used) >= 4 and f"Group 0: upgrade from {len(used)} control GCP(s) ({', '.join(used)})" in md
    assert "changed after this upgrade" not in md
    # the run read the operator's working set, edited after the upgrade: the panel says so
    shutil.copy(state.site.root / "gcps.geojson", lay.gcps)
    report = json.loads(lay.report.read_text())
    report["gcp_file"] = str(lay.gcps)
    lay.report.write_text(json.dumps(report))
    t = lay.upgrade_record(0).stat().st_mtime
    os.utime(lay.gcps, (t + 60, t + 60))
    md = provenance_markdown(out)
    assert "the viewer's working GCP set" in md and "changed after this upgrade" in md


def test_observations_in_unregistered_tiles_are_not_counted_as_usable(tiny_run, small_site, tmp_path):
    import copy

    from aerec_viewer.results import gcp_readiness
    from recon_core.io.site import load_site

    state, _ = tiny_run
    m = copy.deepcopy(state.models[0])
    site = load_site(state.site.root)
    s = open_session(tmp_path / "out", site)
    g = next(p for p in s.gcps if len(p.observations) >= 2 and all(im in m.images for im in p.observations))
    ok, txt = gcp_readiness(s, {0: m})[g.id]
    assert ok and f"observed in {len(g.observations)} usable image(s)" in txt
    lost = sorted(g.observations)[0]
    for t, tile in enumerate(m.tiles):                  # as if that image's tiles had failed
        if tile.image == lost:
            m.registered[t] = False
    ok, txt = gcp_readiness(s, {0: m})[g.id]
    assert f"observed in {len(g.observations) - 1} usable image(s)" in txt
    assert f"not usable: {lost} (its tile there is not registered)" in txt


def _truth_gcps(site_root):
    return json.loads((site_root / "truth" / "gcps_truth.json").read_text())["gcps"]


def test_prediction_of_a_gcp_in_another_image_against_the_truth(tiny_run):
    """On the synthetic `tiny` site, with noise-free clicks: placed in two images, a GCP is
    predicted in the third by triangulation; placed in one, by the sparse surface and refined by
    matching along the ray's plausible depths. Errors against the true projections."""
    from recon_core.euclidean.gcp_transfer import predict_observation

    state, _ = tiny_run
    m = state.models[0]
    images = {im.name: im for im in state.site.images}
    two, one_geo, one_ref, reach = [], [], [], []
    for g in _truth_gcps(state.site.root):
        tob = {k: tuple(v) for k, v in g["true_observations"].items()}
        for dst in sorted(tob):
            others = {k: v for k, v in tob.items() if k != dst}
            p = predict_observation(m, images, others, dst) if len(others) >= 2 else None
            if p is not None:
                two.append(np.hypot(p.col - tob[dst][0], p.row - tob[dst][1]))
                reach.append(p.reach_px)
            for src in sorted(tob):
                if src == dst:
                    continue
                q = predict_observation(m, images, {src: tob[src]}, dst)
                if q is not None and q.score is not None:
                    one_geo.append(np.hypot(q.geometric[0] - tob[dst][0], q.geometric[1] - tob[dst][1]))
                    one_ref.append(np.hypot(q.col - tob[dst][0], q.row - tob[dst][1]))
    two = np.array(two)
    assert len(two) >= 20 and np.median(two) < 0.5 and np.mean(two < 1.0) > 0.9, np.round(two, 2)
    assert len(one_ref) >= 15
    assert np.median(one_ref) < 0.5 and np.median(one_ref) < 0.2 * np.median(one_geo), \
        (np.median(one_ref), np.median(one_geo))
    # a triangulated prediction says how well its noise-free observations agree (about the
    # sparse reprojection error of the tile cameras, not zero and not pixels)
    r = np.array(reach, float)
    assert np.all(np.isfinite(r)) and 0.0 < np.median(r) < 1.0, np.round(r, 2)


def test_predict_then_accept_from_the_gcp_panel(live):
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    img = app.pick_plane.window.image
    cat = {c.id: c for c in app.session.catalogue}
    gid = next(g.id for g in app.session.gcps       # one that earlier tests left as the site has it
               if len([im for im in g.observations if im != img]) >= 2 and g.id in cat
               and g.observations == cat[g.id].observations and img in g.observations)
    app.call(lambda: gp.refresh(select=gid))
    # the site's own click, for comparison (earlier tests may have moved the working copy's)
    before = next((c.observations.get(img) for c in app.session.catalogue if c.id == gid), None)
    app.call(lambda: remove_observation(app.session, gid, img))
    pred = app.call(gp._predict)
    assert pred.image == img and not gp.accept.disabled and gp.accept.label.startswith(f"Accept: {gid}")
    assert np.hypot(pred.col - before[0], pred.row - before[1]) < 6.0   # noisy clicks, short baseline
    app.call(gp._accept)
    assert app.session.get(gid).observations[img] == (pred.col, pred.row) and gp.accept.disabled


def test_residual_vectors_on_the_image_plane(live):
    """Each GCP observed in the plane's image and in another image of its group gets a segment
    from its observation along its reprojection residual (x residual_scale()); a misclick of a few
    pixels shows as a long red one."""
    from recon_core.euclidean.gcp_transfer import observation_residuals

    app, events, trace, out, site, cfg = live
    app.wait_idle()
    if app.pick_plane is None:
        app.call(lambda: app.show_image_plane(wait=True))
    img = app.pick_plane.window.image
    model = next(m for m in app.models.values() if img in m.images)
    vecs = app.call(app.residual_vectors)
    expect = {g.id for g in app.session.gcps if img in g.observations
              and img in observation_residuals(model, g.observations)}
    assert set(vecs) == expect and len(expect) >= 3
    gid = sorted(expect)[0]
    (c, r), _ = vecs[gid]
    app.call(lambda: add_observation(app.session, gid, img, c + 4.0, r - 3.0))   # a misclick
    app.call(lambda: app.gcps_changed(select=gid))
    (c2, r2), (dx, dy) = app.call(app.residual_vectors)[gid]
    assert (c2, r2) == (c + 4.0, r - 3.0) and np.hypot(dx, dy) > 1.0
    seg = app._residual_nodes[0]
    assert len(seg.points) == len(expect)
    k = list(app.call(app.residual_vectors)).index(gid)
    a, b = np.asarray(seg.points[k], float)
    pl = app.pick_plane
    np.testing.assert_allclose(b - a, pl.point_of(c2 + app.residual_scale() * dx, r2 + app.residual_scale() * dy)
                               - pl.point_of(c2, r2), atol=1e-3)
    assert tuple(np.asarray(seg.colors)[k, 0]) == (220, 30, 30)
    # the magnification follows the window: ~5 % of it per pixel of residual, 20 at least
    w = pl.window
    assert app.residual_scale() >= max(20.0, 0.05 * max(w.width, w.height))
    assert f"x{app.residual_scale():g}" in app._residual_nodes[1].text
    app.call(lambda: undo(app.session))
    app.call(lambda: app.gcps_changed(select=gid))


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


def test_gcp_state_table_shows_each_images_state(tiny_run, tmp_path):
    import copy

    from aerec_viewer.results import gcp_state_table
    from recon_core.io.site import load_site

    state, _ = tiny_run
    m = copy.deepcopy(state.models[0])
    s = open_session(tmp_path / "out", load_site(state.site.root))
    imgs = sorted(s.images)
    g = next(p for p in s.gcps if len(p.observations) == len(imgs))
    md = gcp_state_table(s, {0: m}, imgs)
    assert md.splitlines()[0] == "| GCP | role | " + " | ".join(imgs) + " |"
    row = next(ln for ln in md.splitlines() if ln.startswith(f"| {g.id} |"))
    assert row.count("placed") == len(imgs)
    for t, tile in enumerate(m.tiles):                  # the first image's tiles fail
        if tile.image == imgs[0]:
            m.registered[t] = False
    remove_observation(s, g.id, imgs[1])
    row = next(ln for ln in gcp_state_table(s, {0: m}, imgs).splitlines() if ln.startswith(f"| {g.id} |"))
    cells = [c.strip() for c in row.strip("|").split("|")][2:]
    assert cells[0] == "**unusable**" and cells[1] == "predicted" and cells[2] == "placed"
    remove_observation(s, g.id, imgs[2])              # nothing usable left to predict from
    row = next(ln for ln in gcp_state_table(s, {0: m}, imgs).splitlines() if ln.startswith(f"| {g.id} |"))
    cells = [c.strip() for c in row.strip("|").split("|")][2:]
    assert cells == ["**unusable**", "-", "-"]


def test_an_empty_model_update_is_folded_without_error():
    """A joint reconstruction's update can hold no point of one group yet (its images not
    registered): the viewer folds it as an empty batch."""
    from aerec_viewer.worker import _batch

    b = _batch(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0), 0.0)
    assert b.xyz.shape == (0, 3) and b.rgb.shape == (0, 3)


def test_placing_in_other_images_keeps_only_predictions_that_agree(tiny_run, monkeypatch):
    """"Place it in its other images" from one noise-free click per GCP (the `tiny` truth):
    what it records is close to the true projections; and a match that NCC accepts but that is
    wrong (3 px off, across the epipolar lines, which run mostly along the columns here: an
    error along them is a depth the check cannot tell from the truth) is left to the operator
    with the reason, not recorded."""
    import recon_core.euclidean.gcp_transfer as pr

    state, _ = tiny_run
    m = state.models[0]
    images = {im.name: im for im in state.site.images}

    def each_gcp_from_one_click():
        """(true observations, place_in_other_images from the first image's true pixel)."""
        for g in _truth_gcps(state.site.root):
            tob = {k: tuple(v) for k, v in g["true_observations"].items()}
            if len(tob) >= 3:
                src = sorted(tob)[0]
                yield tob, pr.place_in_other_images(m, images, {src: tob[src]})

    errs, n_left = [], 0
    for tob, (placed, left, hints) in each_gcp_from_one_click():
        n_left += len(left)
        errs += [np.hypot(p.col - tob[im][0], p.row - tob[im][1]) for im, p in placed.items()]
    errs = np.array(errs)
    assert len(errs) >= 8 and np.median(errs) < 0.5 and errs.max() < 2.0, (np.round(errs, 2), n_left)

    real = pr.refine_by_matching

    def wrong(*a, **k):                  # a confident match 3 px off
        got = real(*a, **k)
        return None if got is None else ((got[0][0], got[0][1] + 3.0), 0.97)

    monkeypatch.setattr(pr, "refine_by_matching", wrong)
    refused = 0
    for tob, (placed, left, hints) in each_gcp_from_one_click():
        assert all(p.score is None for p in placed.values())          # no wrong match recorded
        assert all(np.hypot(p.col - tob[im][0], p.row - tob[im][1]) < 2.0 for im, p in placed.items())
        refused += sum("does not agree" in why for why in left.values())
        assert set(hints) <= set(left) and all(h.score is None for h in hints.values())
    assert refused >= 4, refused


def test_the_viewer_refuses_a_blank_image_before_computing(small_site, tmp_path):
    """What `aerec run` refuses before any compute, the viewer's worker refuses too, naming the
    file: a blank image no longer runs sparse and dense to fail on the GCPs."""
    from recon_core.config import preset
    from tests.conftest import write_tiff

    write_tiff(small_site / "images" / "b.tif", np.full((48, 64), 812, np.uint16), when="2020:01:03 10:00:00")
    w = ReconWorker(small_site, tmp_path / "out", preset("tiny"), mode="run", until="sparse").start()
    assert w.join(60)
    snap = w.snapshot()
    assert snap.status == "failed" and "b.tif" in snap.error and "is blank" in snap.error, snap.error
    assert not (tmp_path / "out" / "affine").exists()


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


def test_a_slow_page_lowers_the_point_budget_and_says_so(live):
    """Orbiting at 3 view updates/s (software WebGL at 150 k points) lowers the budget after the
    gesture; the operator's own budget is kept from then on."""
    app = live[0]
    s = app.scene.settings
    before, tiles = s.budget, s.tiles
    try:
        app.call(lambda: setattr(s, "budget", 150_000))
        t0 = time.monotonic() - 10.0
        for k in range(12):
            app.view_rate.moved(99, t0 + k / 3.0)
        app.call(app._govern_budget)
        assert s.budget < 150_000 and app.g_budget.value == s.budget // 1000
        assert "budget lowered from 150 k" in app.g_budget_note.content
        assert sum("budget lowered" in text for _, text in app.worker.snapshot().messages) == 1
        # the operator sets it: kept, however slow
        app.governor.user_set = True
        app.call(lambda: setattr(s, "budget", 150_000))
        for k in range(12):
            app.view_rate.moved(99, t0 + 5.0 + k / 3.0)
        app.call(app._govern_budget)
        assert s.budget == 150_000
    finally:
        app.governor.user_set = False
        app.g_budget_note.content = ""
        app.call(lambda: (setattr(s, "budget", before), setattr(s, "tiles", tiles), app._force()))


def test_the_gcp_list_names_each_gcps_role_and_images_placed(live):
    """The list an operator scans: 'id · role · placed/registered', and choosing an entry
    selects the GCP behind it."""
    app = live[0]
    gp = app.gcp_panel
    app.call(lambda: gp.refresh())
    s = app.session
    if not s.ids:
        pytest.skip("no GCP in the working set")
    registered = app.call(gp._registered_images)
    for gid in s.ids:
        g = s.get(gid)
        entry = gp.option_of(gid)
        assert entry in gp.select.options and gp.id_of(entry) == gid
        role = g.role if g.enabled else "off"
        assert entry == f"{gid} · {role} · {len(set(g.observations) & registered)}/{len(registered)}"
    gid = s.ids[-1]
    app.call(lambda: gp.select_id(gid))
    assert gp.selected() == gid and gp.select.value == gp.option_of(gid)
    app.call(lambda: gp.select_id(None))
    assert gp.selected() is None and gp.select.value == gp.NEW


def test_shift_click_zooms_toward_the_spot_under_the_cursor(live):
    """viser's wheel zooms toward the view's centre; shift+click moves the camera halfway along
    the click ray to what it meets (the picking plane here), keeping the orientation, so the spot
    stays under the cursor; ctrl+shift+click goes back."""
    import contextlib
    from types import SimpleNamespace

    app = live[0]
    pl = app.pick_plane
    assert pl is not None
    spot_true = pl.point_of(pl.window.col0 + 0.3 * pl.window.width, pl.window.row0 + 0.6 * pl.window.height)
    o = spot_true + np.array([120.0, -80.0, 900.0])
    look = o + np.array([0.0, 300.0, -700.0])
    client = SimpleNamespace(camera=SimpleNamespace(position=tuple(o), look_at=tuple(look)),
                             atomic=contextlib.nullcontext)
    d = spot_true - o
    spot = app.call(lambda: app.zoom_at(client, o, d, 2.0))
    assert np.allclose(spot, spot_true, atol=1e-6 * np.linalg.norm(d))
    p1, l1 = np.asarray(client.camera.position), np.asarray(client.camera.look_at)
    assert np.allclose(p1, o + 0.5 * d)                      # on the ray, half the way
    assert np.allclose(l1 - p1, look - o)                    # same orientation
    app.call(lambda: app.zoom_at(client, p1, d, 0.5))
    assert np.allclose(np.asarray(client.camera.position), o, atol=1e-6 * np.linalg.norm(d))
    # a ray that meets nothing: the depth of the view's centre
    up = np.array([0.0, 0.0, 1.0])
    spot = app.call(lambda: app.zoom_at(client, o, up + 1e-3, 2.0))
    assert np.all(np.isfinite(spot))
