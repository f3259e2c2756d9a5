"""The viewer as a headless server running the real pipeline on a small site: points grow, tiles
appear, progress ends, GCP picks through the click handlers' own functions, the loupe, the
working set's navigation, upgrade, DSM panel, reopening. The display maths, the worker and the
GCP session have their own files."""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np
import pytest

from aerec_viewer import display as dp
from aerec_viewer.gcp_marks import MARK_RING_PX
from aerec_viewer.gcp_session import (
    GcpError,
    add_observation,
    can_undo,
    delete_gcp,
    open_session,
    redo,
    remove_observation,
    set_affine_position,
    undo,
)
from aerec_viewer.worker import ReconWorker


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
    while app.picking.plane is None and time.time() - t1 < 30:
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
    assert app.recon.g_progress.value == 100.0
    assert "finished" in app.recon.g_status.content
    assert f"{len(g0.tiles)} / {g0.total_tiles}" in app.recon.g_stats.content
    assert "affine frame" in app.recon.g_frame.content


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
    app.call(lambda: (setattr(app.scene.settings, "budget", max(10, n_all // 4)), app.force()))
    app.wait_idle()
    assert app.scene.displayed_points() < 0.5 * n_all
    app.call(lambda: (setattr(app.scene.settings, "budget", 150_000), app.force()))
    app.wait_idle()
    assert app.scene.displayed_points() == n_all


def _ray_to(app, col, row):
    p = app.picking.plane
    target = p.point_of(col, row)
    origin = target + np.array([3.0, -4.0, 40.0]) * p.render_width / 40.0
    return origin, target - origin


def test_gcp_picks_through_the_click_handlers_then_upgrade(live):
    app, events, trace, out, site, cfg = live
    assert app.picking.plane is not None
    img = app.picking.plane.window.image
    # a new GCP from typed coordinates, then a click on the image plane observes it
    gp = app.gcp_panel
    app.call(lambda: gp.select_id(None))
    app.wait_idle()                      # the list's change is applied (it clears the fields)
    app.call(lambda: (setattr(gp.gid, "value", "NEW-1"),
                      setattr(gp.x, "value", 55.65), setattr(gp.y, "value", -21.23),
                      setattr(gp.h, "value", 2300.0)))
    o, d = _ray_to(app, 123.25, 200.75)
    pix = app.call(lambda: app.gcp.on_plane_click(o, d))
    assert pix is not None and abs(pix[0] - 123.25) < 1e-3 and abs(pix[1] - 200.75) < 1e-3
    assert app.gcp.last_click[:2] == ("NEW-1", img)
    n_img = len(app.call(gp._registered_images))
    assert f"| **NEW-1** | control | 1 / {n_img} | - | - |" in gp.listing.content      # the working set's table
    saved = json.loads((out / "gcps.geojson").read_text())
    feat = {f["properties"]["id"]: f for f in saved["features"]}["NEW-1"]
    assert np.allclose(feat["properties"]["observations"][img], [123.25, 200.75], atol=1e-3)
    # a second click on the same GCP replaces its observation in that image
    o, d = _ray_to(app, 130.0, 190.0)
    app.call(lambda: app.gcp.on_plane_click(o, d))
    assert np.allclose(app.session.get("NEW-1").observations[img], (130.0, 190.0), atol=1e-3)
    # the cloud pick: a ray through a displayed point sets the GCP's affine position
    ch = app.scene._clouds[(0, "sparse")].chunks[0]
    target = ch.xyz[5].astype(float)
    app.call(app.gcp.arm_cloud_pick)
    xyz = app.call(lambda: app.gcp.on_cloud_click("NEW-1", target + [0, 0, 50.0], [0, 0, -1.0]))
    T = app.scene._clouds[(0, "sparse")].transform
    assert np.allclose(T.apply(xyz[None])[0], target, atol=1e-2)
    assert app.gcp.armed is None and 0 in app.session.get("NEW-1").affine_picked
    # markers: on the plane for observations in this image, on the cloud for placed GCPs
    app.wait_idle()
    names = set(app.marks.items)
    assert "/gcp/plane_marks/NEW-1" in names and "/gcp/cloud/g0/NEW-1" in names
    # markers are rings that keep their size on screen: zooming in 4x shrinks them 4x in the
    # world (the view that moved last sets it)
    from types import SimpleNamespace

    def view(d):
        return SimpleNamespace(client=SimpleNamespace(client_id=99), position=np.array([0.0, 0.0, d]),
                               wxyz=np.array([1.0, 0.0, 0.0, d]), look_at=np.zeros(3), fov=0.8,
                               image_height=900)

    app.views.camera_update(view(400.0))
    app.wait_idle()
    r_far = app.marks.items["/gcp/plane_marks/NEW-1"].radius
    app.views.camera_update(view(100.0))
    app.wait_idle()
    r_near = app.marks.items["/gcp/plane_marks/NEW-1"].radius
    assert r_far / r_near == pytest.approx(4.0, rel=1e-6)
    assert r_near == pytest.approx(MARK_RING_PX * 2 * 100.0 * np.tan(0.4) / 900)
    app.call(lambda: delete_gcp(app.session, "NEW-1"))
    app.call(lambda: app.gcp.changed(select=None))
    assert "NEW-1" not in app.session.ids

    # the upgrade with the site's GCPs (copied into the working set on first opening)
    assert not app.g_upgrade.disabled, app.g_ready.content
    outcome = app.call(app.gcp.do_upgrade)
    assert outcome.ok and app.frame == "euclidean"
    res = outcome.results[0].to_dict()
    checks = [p for p in res["points"] if p["status"] == "check"]
    assert checks and res["stats"]["check"]["n"] == len(checks)
    assert res["stats"]["check"]["rmse_3d_m"] < 5.0
    md = app.g_upgrade_md.content
    assert "| GCP | role | status | dE m | dN m | dU m | reproj px |" in md and "check" in md
    assert "N = 4" in md or "LOO" in md.upper() or "loo" in md
    # the working set's table gives each scored GCP its error in metres, a check point's its residual
    chk = checks[0]
    assert (f"| {chk['id']} | check |" in gp.listing.content
            and f"{chk['dE']:+.2f} / {chk['dN']:+.2f} / {chk['dU']:+.2f} |" in gp.listing.content)
    # the metric bend step: said when applied (the 3D view places the clouds by H_A alone)
    applied = outcome.groups[0].metric.get("applied")
    assert ("Metric bend step: a horizontal warp of" in md) == bool(applied)
    assert not (out / "viewer_upgrade.json").exists()      # one upgrade record: the pipeline's
    assert "stops after the sparse stage" in app.worker.rerun_from("upgrade")   # --until sparse
    app.wait_idle()
    st = app.scene._clouds[(0, "sparse")]
    assert st.transform.kind == "euclidean" and "Euclidean frame" in app.recon.g_frame.content
    # metres, z up: the ENU cloud spans a plausible site and its heights are metric
    P = np.concatenate([c.xyz for c in st.chunks]).astype(float)
    assert 20.0 < np.ptp(P[:, 0]) < 20_000.0 and np.ptp(P[:, 2]) < np.ptp(P[:, 0])
    app.call(lambda: app.set_frame("affine"))
    assert app.scene._clouds[(0, "sparse")].transform.kind == "affine"


def test_nudges_move_the_selected_observation_in_the_image_shown(live):
    """The nudge buttons: the selected GCP's observation in the plane's image moves by the step
    (0.1 px by default); successive nudges are one Undo; a GCP not observed there is refused."""
    app, *_ = live
    gp = app.gcp_panel
    img = app.picking.plane.window.image
    gid = next(g.id for g in app.session.gcps if img in g.observations)
    c0, r0 = app.session.get(gid).observations[img]
    app.call(lambda: gp.select_id(gid))
    app.wait_idle()
    for _ in range(3):
        app.call(lambda: gp.nudge(0.1, 0.0))
    app.call(lambda: gp.nudge(0.0, -0.1))
    c, r = app.session.get(gid).observations[img]
    assert (c - c0, r - r0) == pytest.approx((0.3, -0.1), abs=1e-9)
    assert can_undo(app.session).startswith("nudge")
    app.call(gp._undo)                       # one step back to where the nudges started
    assert app.session.get(gid).observations[img] == pytest.approx((c0, r0), abs=1e-9)
    other = next((g.id for g in app.session.gcps if img not in g.observations), None)
    if other is not None:
        app.call(lambda: gp.select_id(other))
        app.wait_idle()
        with pytest.raises(GcpError, match="no observation"):
            app.call(lambda: gp.nudge(0.1, 0.0))


def test_markers_go_out_and_come_back_as_csv(live):
    """Export: the working set as CSV (what `aerec gcps convert` reads), sent to the tab.
    Import: a known id takes the file's position and observations, a new one is added, all as
    one Undo; a file naming an image the site lacks changes nothing."""
    from types import SimpleNamespace

    app, *_ = live
    gp = app.gcp_panel
    sent = []
    client = SimpleNamespace(send_file_download=lambda name, data: sent.append((name, data)))
    text = app.call(lambda: gp.export_markers(client))
    assert sent and sent[0][0].endswith(".csv") and sent[0][1].decode() == text
    n = len(app.session.gcps)
    g0 = copy.deepcopy(app.session.gcps[0])
    img = sorted(app.session.images)[0]
    lines = text.splitlines()
    moved = [ln.replace(f"{g0.h:.4f}", f"{g0.h + 1.0:.4f}") for ln in lines if ln.startswith(g0.id + ",")]
    new = f"CSV-1,check,{g0.lon:.9f},{g0.lat + 1e-4:.9f},{g0.h:.4f},4979,,{img},10.000,20.000"
    csv_in = "\n".join([lines[0], *moved, new]) + "\n"
    added, updated = app.call(lambda: gp.import_markers("mine.csv", csv_in.encode()))
    assert added == ["CSV-1"] and updated == [g0.id] and len(app.session.gcps) == n + 1
    assert app.session.get(g0.id).h == pytest.approx(g0.h + 1.0, abs=1e-3)
    assert app.session.get("CSV-1").observations == {img: (10.0, 20.0)}
    assert can_undo(app.session).startswith("import")
    app.call(gp._undo)
    assert "CSV-1" not in app.session.ids and app.session.get(g0.id).h == pytest.approx(g0.h, abs=1e-4)
    v = app.session.version
    with pytest.raises(GcpError, match="nothing imported.*no image"):
        app.call(lambda: gp.import_markers("bad.csv", (lines[0] + "\nX,control,1,2,3,4979,,nope.tif,1,2\n").encode()))
    with pytest.raises(GcpError, match="bad.csv: missing column"):
        app.call(lambda: gp.import_markers("bad.csv", b"id,x\nA,1\n"))
    assert app.session.version == v


def test_loupe_first_click_zooms_second_click_places(live):
    """With "Click zooms in first": a click on the whole image opens the loupe there (nothing
    recorded, the plane shows 40 x 40 full-resolution pixels losslessly), a click in the loupe is
    the observation, to the same sub-pixel precision, and the plane goes back to the region."""
    from aerec_viewer.picking import LOUPE_PX

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    gid = app.session.ids[0]
    app.call(lambda: gp.refresh(select=gid))
    app.call(lambda: setattr(gp.zoom_click, "value", True))
    try:
        if app.picking.plane is None:
            app.call(lambda: app.picking.show(wait=True))
        whole = app.picking.plane.window
        img = whole.image
        before = dict(app.session.get(gid).observations)
        o, d = _ray_to(app, 150.4, 160.6)
        assert app.call(lambda: app.gcp.on_plane_click(o, d)) is None
        assert app.session.get(gid).observations == before              # nothing recorded
        win = app.picking.plane.window
        assert app.picking.loupe is not None and win == app.picking.loupe[0] and win.image == img
        assert (win.width, win.height) == (LOUPE_PX, LOUPE_PX) and win.contains([(150.4, 160.6)])[0]
        assert not gp.leave_loupe.disabled
        o, d = _ray_to(app, 152.37, 158.81)
        pix = app.call(lambda: app.gcp.on_plane_click(o, d))
        assert pix is not None and abs(pix[0] - 152.37) < 1e-3 and abs(pix[1] - 158.81) < 1e-3
        assert np.allclose(app.session.get(gid).observations[img], (152.37, 158.81), atol=1e-3)
        assert app.picking.loupe is None and app.picking.plane.window == whole and gp.leave_loupe.disabled
        # Leave the loupe records nothing
        o, d = _ray_to(app, 300.0, 100.0)
        app.call(lambda: app.gcp.on_plane_click(o, d))
        assert app.picking.loupe is not None
        app.call(app.picking.close_loupe)
        assert app.picking.loupe is None and app.picking.plane.window == whole
        assert np.allclose(app.session.get(gid).observations[img], (152.37, 158.81), atol=1e-3)
    finally:
        app.call(lambda: undo(app.session))
        app.call(lambda: app.gcp.changed(select=gid))
        app.call(lambda: setattr(gp.zoom_click, "value", False))


def test_next_gcp_with_a_loupe_open_records_nothing_at_the_last_ones_spot(live):
    """The trial: a loupe open on GCP A's spot, N selects B, and the next click recorded B at A's
    spot. Now N closes the loupe (it was A's): the next click opens B's own loupe, nothing is
    recorded, and B's observations are unchanged."""
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    ids = app.session.ids
    g1 = ids[0]
    app.call(lambda: gp.refresh(select=g1))
    app.call(lambda: setattr(gp.zoom_click, "value", True))
    before = {g: dict(app.session.get(g).observations) for g in ids}
    try:
        if app.picking.plane is None:
            app.call(lambda: app.picking.show(wait=True))
        o, d = _ray_to(app, 150.4, 160.6)
        assert app.call(lambda: app.gcp.on_plane_click(o, d)) is None           # A's loupe
        assert app.picking.loupe is not None and app.picking.loupe_gcp == g1
        g2 = app.call(lambda: gp.step_gcp(+1))                              # N
        app.wait_idle()
        assert g2 != g1 and app.picking.loupe is None                        # A's loupe is gone
        o, d = _ray_to(app, 151.0, 159.0)
        assert app.call(lambda: app.gcp.on_plane_click(o, d)) is None           # B's own loupe opens
        assert app.picking.loupe_gcp == g2
        assert {g: dict(app.session.get(g).observations) for g in ids} == before
        # a loupe left open by the list's selection of another GCP cannot place it either
        app.picking.loupe_gcp = g1
        o, d = _ray_to(app, 151.5, 159.5)
        with pytest.raises(GcpError, match="the loupe shows"):
            app.call(lambda: app.gcp.on_plane_click(o, d))
        assert {g: dict(app.session.get(g).observations) for g in ids} == before
    finally:
        app.call(app.picking.close_loupe)
        app.call(lambda: setattr(gp.zoom_click, "value", False))
        app.call(lambda: app.gcp.changed(select=g1))


def test_another_tabs_click_in_a_loupe_records_nothing(live):
    """The trial: tab A opens the loupe; tab B sees its 40 pixels stretched over the plane it
    took for the whole image, and its ordinary click moved a GCP by 9.5 px. Now a click in a
    loupe is recorded only from the tab that opened it."""
    from types import SimpleNamespace

    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    def tab(cid):
        return SimpleNamespace(client_id=cid, camera=SimpleNamespace(
            position=(0.0, 0.0, 1.0), look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0), far=1e4))
    a, b = tab(9101), tab(9102)
    gid = app.session.ids[0]
    app.call(lambda: gp.refresh(select=gid))
    app.call(lambda: setattr(gp.zoom_click, "value", True))
    before = dict(app.session.get(gid).observations)
    n_undo = len(app.session._undo)
    try:
        if app.picking.plane is None:
            app.call(lambda: app.picking.show(wait=True))
        o, d = _ray_to(app, 150.4, 160.6)
        assert app.call(lambda: app.gcp.on_plane_click(o, d, a)) is None         # A's loupe
        o, d = _ray_to(app, 152.0, 158.0)
        with pytest.raises(GcpError, match="another tab's loupe"):
            app.call(lambda: app.gcp.on_plane_click(o, d, b))
        assert dict(app.session.get(gid).observations) == before and app.picking.loupe is not None
        assert app.call(lambda: app.gcp.on_plane_click(o, d, a)) is not None     # A places it
        assert len(app.session._undo) == n_undo + 1
    finally:
        for _ in range(len(app.session._undo) - n_undo):
            app.call(lambda: undo(app.session))
        app.call(app.picking.close_loupe)
        app.call(lambda: setattr(gp.zoom_click, "value", False))
        app.call(lambda: app.gcp.changed(select=gid))


def test_a_click_in_the_loupe_walks_on_to_the_gcps_next_image(live):
    """With "Then its next image": after a click in the loupe records an observation, the next
    image without one opens in the loupe at the GCP's prediction (close to its true pixel);
    Enter there records it and walks on; once every image has one, the plane stays."""
    app, events, trace, out, site, cfg = live
    if not (site / "truth" / "gcps_truth.json").exists():
        pytest.skip("needs the synthetic site's truth")
    gp = app.gcp_panel
    truth = {g["id"]: {k: tuple(v) for k, v in g["true_observations"].items()} for g in json.loads((site / "truth" / "gcps_truth.json").read_text())["gcps"]}
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
        app.call(lambda: app.picking.show(wait=True))
        o, d = _ray_to(app, *tob[first])
        app.call(lambda: app.gcp.on_plane_click(o, d))                     # opens the loupe
        o, d = _ray_to(app, *tob[first])
        app.call(lambda: app.gcp.on_plane_click(o, d))                     # records, walks on
        app.wait_idle()
        nxt = gp.image.value
        assert nxt != first and nxt in tob and app.picking.loupe is not None and app.picking.loupe[0].image == nxt
        assert np.hypot(*(np.asarray(app.picking.loupe[1]) - tob[nxt])) < 3.0, (app.picking.loupe[1], tob[nxt])
        assert gp.prediction is not None and gp.prediction[1].image == nxt
        # an offer made stale before it is shown (the operator pressed Undo meanwhile) is dropped
        app.call(app.picking.close_loupe)
        app.call(gp.drop_prediction)
        pred = gp.prediction
        app.call(lambda: gp.show_hint(gid, predict_now(nxt), None) or undo(app.session))
        app.wait_idle()
        assert gp.prediction is None and app.picking.loupe is None
        app.call(lambda: redo(app.session))
        app.call(lambda: gp.show_hint(gid, predict_now(nxt), None))
        app.wait_idle()
        assert gp.prediction is not None and app.picking.loupe is not None and pred is None
        for _ in range(len(tob) - 1):                                   # Enter on each in turn
            app.call(gp._accept)
            app.wait_idle()
        obs = app.session.get(gid).observations
        assert set(obs) == set(tob)
        assert app.picking.loupe is None and "N for the next GCP" in gp.status.content
        err = [np.hypot(obs[k][0] - tob[k][0], obs[k][1] - tob[k][1]) for k in tob if k != first]
        assert max(err) < 1.5, err
    finally:
        app.call(app.picking.close_loupe)
        for im in list(app.session.get(gid).observations):
            app.call(lambda im=im: remove_observation(app.session, gid, im))
        for im, xy in saved.items():
            app.call(lambda im=im, xy=xy: add_observation(app.session, gid, im, *xy))
        app.call(lambda: setattr(gp.zoom_click, "value", False))
        app.call(lambda: app.gcp.changed(select=gid))


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
    app.call(lambda: app.gcp.changed(select=gid))
    line = next(ln for ln in gp.info.content.splitlines() if ln.startswith(f"- {im}"))
    assert "check it" in line, gp.info.content
    try:
        app.call(lambda: setattr(gp.jump, "value", im))
        app.wait_idle()
        assert gp.jump.value == gp.JUMP_NONE and gp.image.value == im
        assert app.picking.loupe is not None and app.picking.loupe[0].image == im
        assert np.allclose(app.picking.loupe[1], (c + 6.0, r))
    finally:
        app.call(app.picking.close_loupe)
        app.call(lambda: undo(app.session))
        app.call(lambda: app.gcp.changed(select=gid))
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
        app.call(lambda: app.gcp.changed(select=target))
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
    app.call(lambda: app.gcp.changed(select=gid))


def test_an_image_left_by_place_all_opens_in_the_loupe_and_enter_accepts(live, monkeypatch):
    """When "Place it in its other images" leaves an image to the operator with a prediction,
    the plane switches to that image and the loupe opens at the predicted pixel; accepting
    records exactly that pixel there; nothing else was recorded."""
    from aerec_viewer import gcp_actions as gpm
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
        assert gp.image.value == target and app.picking.plane.window.image == target
        assert app.picking.loupe is not None and app.picking.loupe[0].image == target
        assert np.allclose(app.picking.loupe[1], (201.25, 143.5)) and app.picking.loupe[0].contains([(201.25, 143.5)])[0]
        assert gp.prediction is not None and not gp.accept.disabled
        app.call(gp._accept)
        assert app.session.get(gid).observations[target] == (201.25, 143.5)
    finally:
        app.call(app.picking.close_loupe)
        app.call(lambda: undo(app.session))
        if had is not None:
            app.call(lambda: add_observation(app.session, gid, target, *had))
        app.call(lambda: app.gcp.changed(select=gid))


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
    if app.picking.plane is None:
        app.call(lambda: app.picking.show(wait=True))
    o, d = _ray_to(app, 120.0, 130.0)
    with pytest.raises(GcpError, match=f"another tab changed the GCP to {g2}"):
        app.call(lambda: app.gcp.on_plane_click(o, d, a))
    assert {g: dict(app.session.get(g).observations) for g in (g1, g2)} == before
    n_undo = len(app.session._undo)
    try:
        assert app.call(lambda: app.gcp.on_plane_click(o, d, b)) is not None          # B: its own GCP
        assert app.call(lambda: app.gcp.on_plane_click(o, d, a)) is not None          # A, warned: goes through
        assert len(app.session._undo) == n_undo + 2
        # one tab's own actions that change the list on the server (Create, Delete, Undo, a
        # selection made for it) never refuse its click
        app.call(lambda: gp.refresh(select=g1))
        assert app.call(lambda: app.gcp.on_plane_click(o, d, b)) is not None
        assert len(app.session._undo) == n_undo + 3
    finally:
        for _ in range(len(app.session._undo) - n_undo):
            app.call(lambda: undo(app.session))
        app.call(lambda: app.gcp.changed(select=g1))
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
        app.call(lambda: app.gcp.on_plane_click(o, d))
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


def test_a_flat_gcp_refusal_offers_what_the_page_can_do(live, monkeypatch):
    """The refusal of GCPs nearly on one plane names the Results tab's checkbox (not `aerec run
    --config`, which the page cannot pass), and the checkbox sets upgrade.allow_flat_gcps for the
    page's upgrades and the DSM they recompute."""
    from aerec_viewer import gcp_controller
    from recon_core.errors import ReconstructionError

    app = live[0]

    def refuse(*a, **k):
        raise ReconstructionError("refused: the 4 control GCPs lie near one plane. To go on anyway, set "
                                  "upgrade.allow_flat_gcps = true (aerec run --config FILE).")
    monkeypatch.setattr(gcp_controller, "run_upgrade", refuse)
    with pytest.raises(ReconstructionError):
        app.call(app.gcp.do_upgrade)
    md = app.g_upgrade_md.content
    assert "Accept GCPs nearly on one plane" in md and "--config" not in md
    before = app.cfg
    try:
        app.call(lambda: app.gcp.allow_flat(True))
        assert app.cfg.upgrade.allow_flat_gcps and app.worker.cfg.upgrade.allow_flat_gcps
    finally:
        app.cfg = app.worker.cfg = before


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
    if app.gcp.upgrade is None:
        app.call(app.gcp.do_upgrade)
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
        outcome = app.call(app.gcp.do_upgrade)
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


def test_predict_then_accept_from_the_gcp_panel(live):
    app, events, trace, out, site, cfg = live
    gp = app.gcp_panel
    img = app.picking.plane.window.image
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
    if app.picking.plane is None:
        app.call(lambda: app.picking.show(wait=True))
    img = app.picking.plane.window.image
    model = next(m for m in app.models.values() if img in m.images)
    vecs = app.call(app.marks.residual_vectors)
    expect = {g.id for g in app.session.gcps if img in g.observations
              and img in observation_residuals(model, g.observations)}
    assert set(vecs) == expect and len(expect) >= 3
    gid = sorted(expect)[0]
    (c, r), _ = vecs[gid]
    app.call(lambda: add_observation(app.session, gid, img, c + 4.0, r - 3.0))   # a misclick
    app.call(lambda: app.gcp.changed(select=gid))
    (c2, r2), (dx, dy) = app.call(app.marks.residual_vectors)[gid]
    assert (c2, r2) == (c + 4.0, r - 3.0) and np.hypot(dx, dy) > 1.0
    seg = app.marks.residual_nodes[0]
    assert len(seg.points) == len(expect)
    k = list(app.call(app.marks.residual_vectors)).index(gid)
    a, b = np.asarray(seg.points[k], float)
    pl = app.picking.plane
    np.testing.assert_allclose(b - a, pl.point_of(c2 + app.marks.residual_scale() * dx, r2 + app.marks.residual_scale() * dy)
                               - pl.point_of(c2, r2), atol=1e-3)
    assert tuple(np.asarray(seg.colors)[k, 0]) == (220, 30, 30)
    # the magnification follows the window: ~5 % of it per pixel of residual, 20 at least
    w = pl.window
    assert app.marks.residual_scale() >= max(20.0, 0.05 * max(w.width, w.height))
    assert f"x{app.marks.residual_scale():g}" in app.marks.residual_nodes[1].text
    app.call(lambda: undo(app.session))
    app.call(lambda: app.gcp.changed(select=gid))


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


def test_a_slow_page_thins_the_display_while_moving_and_says_so(live):
    """Orbiting at 3 view updates/s (software WebGL at 150 k points): after the gesture the
    display while moving is thinned, said under the slider and once in the messages; the
    point budget (at rest) is the operator's and does not move."""
    app = live[0]
    s, mo = app.scene.settings, app.motion
    before = s.budget
    try:
        shown = app.call(app.scene.displayed_points)
        t0 = time.monotonic() - 10.0
        for k in range(12):
            app.view_rate.moved(99, t0 + k / 3.0)
        app.call(lambda: mo.tick())
        assert s.budget == before and app.recon.g_budget.value == before // 1000
        gov = mo.governor
        assert (gov.budget is not None and gov.budget < shown) or gov.shed > 0
        assert app.scene.moving_budget == gov.budget
        note = app.recon.g_budget_note.content
        assert note.startswith("While a view moves:") and "the page moved at 3 frames/s with" in note
        assert sum("While a view moves" in text for _, text in app.worker.snapshot().messages) == 1
        for k in range(12):                                  # slower still: said under the slider only
            app.view_rate.moved(99, t0 + 5.0 + k / 2.0)
        app.call(lambda: mo.tick())
        assert sum("While a view moves" in text for _, text in app.worker.snapshot().messages) == 1
    finally:
        app.call(lambda: (setattr(mo.governor, "budget", None), setattr(mo.governor, "shed", 0),
                          setattr(app.scene, "moving_budget", None), app.scene.sync_moving()))
        app.recon.g_budget_note.content = ""


def test_while_a_view_moves_a_nested_subsample_is_drawn_and_the_rest_comes_back(live):
    """A camera message switches the scene to its moving display: each cloud drawn from a
    subsample of its shown points (about the governor's budget in all, bigger points), the
    kinds the governor sheds hidden; once the views rest everything is as before."""
    from aerec_viewer import motion

    app = live[0]
    sc, mo = app.scene, app.motion
    app.wait_idle()
    shown = app.call(sc.displayed_points)
    assert shown >= 400, shown
    vis_tiles = [(h, h.visible) for h in app.call(sc.tile_nodes)]
    try:
        app.call(lambda: (setattr(mo.governor, "budget", shown // 4), setattr(mo.governor, "shed", 1)))
        mo.moved(time.monotonic())
        app.wait_idle()
        assert mo.moving and sc.moving
        clouds = [st for st in sc._clouds.values() if st.chunks]
        assert all(st.moving is not None for st in clouds)
        assert not any(c.handle.visible for st in clouds for c in st.chunks)
        assert all(st.moving.handle.visible for st in clouds)
        n = sum(st.moving.n for st in clouds)
        assert abs(n - shown / 4) < 0.2 * shown / 4 + 30, (n, shown)     # a hash subsample
        for st in clouds:                                 # drawn from the points shown at rest
            full = {tuple(p) for c in st.chunks for p in np.round(c.xyz.astype(np.float32), 3)}
            assert {tuple(p) for p in np.round(st.moving.handle.points, 3)} <= full
            assert st.moving.handle.point_size >= st.chunks[0].handle.point_size   # capped: 1/200 of the extent
        assert vis_tiles and not any(h.visible for h, _ in vis_tiles)     # shed: the tiles
        time.sleep(motion.REST_MAX_S + 0.3)               # no camera message: the views rest
        app.wait_idle()
        assert not mo.moving and not sc.moving
        assert all(c.handle.visible for st in clouds for c in st.chunks)
        assert not any(st.moving.handle.visible for st in clouds)
        assert [h.visible for h, _ in vis_tiles] == [v for _, v in vis_tiles]
    finally:
        app.call(lambda: (setattr(mo.governor, "budget", None), setattr(mo.governor, "shed", 0),
                          setattr(sc, "moving_budget", None), sc.sync_moving()))


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
    pl = app.picking.plane
    assert pl is not None
    spot_true = pl.point_of(pl.window.col0 + 0.3 * pl.window.width, pl.window.row0 + 0.6 * pl.window.height)
    o = spot_true + np.array([120.0, -80.0, 900.0])
    look = o + np.array([0.0, 300.0, -700.0])
    client = SimpleNamespace(camera=SimpleNamespace(position=tuple(o), look_at=tuple(look)),
                             atomic=contextlib.nullcontext)
    d = spot_true - o
    spot = app.call(lambda: app.views.zoom_at(client, o, d, 2.0))
    assert np.allclose(spot, spot_true, atol=1e-6 * np.linalg.norm(d))
    p1, l1 = np.asarray(client.camera.position), np.asarray(client.camera.look_at)
    assert np.allclose(p1, o + 0.5 * d)                      # on the ray, half the way
    assert np.allclose(l1 - p1, look - o)                    # same orientation
    app.call(lambda: app.views.zoom_at(client, p1, d, 0.5))
    assert np.allclose(np.asarray(client.camera.position), o, atol=1e-6 * np.linalg.norm(d))
    # a ray that meets nothing: the depth of the view's centre
    up = np.array([0.0, 0.0, 1.0])
    spot = app.call(lambda: app.views.zoom_at(client, o, up + 1e-3, 2.0))
    assert np.all(np.isfinite(spot))

