"""The image workspace's HTTP API against a real viewer (the finished `tiny` run, reopened):
every edit changes the working set exactly as the GCP tab's functions do, is saved, and shows
in the 3D viewer's panel; a GCP or observation that is gone is a 409, bad input a 400, each
with one line; tiles are read by windows inside the image."""

from __future__ import annotations

import json
import math
import shutil
import time
import urllib.error
import urllib.request

import cv2
import numpy as np
import pytest

from aerec_viewer.gcp_session import add_observation, delete_gcp, remove_observation, undo
from aerec_viewer.results import predict_unobserved, residual_vectors
from aerec_viewer.workspace import tiles as tiles_mod
from recon_core.io.gcps import read_gcps_geojson


@pytest.fixture(scope="module")
def ws(tiny_run, tmp_path_factory):
    """A viewer reopening a copy of the `tiny` run, with its workspace served."""
    from aerec_viewer.app import ViewerApp

    state, _ = tiny_run
    out = tmp_path_factory.mktemp("ws") / "out"
    shutil.copytree(state.out, out)
    app = ViewerApp(out, state.site.root, None, mode="reopen", port=0)
    app.start()
    t0 = time.time()
    while not app.models and time.time() - t0 < 60:
        time.sleep(0.1)
        app.wait_idle()
    assert app.models, "the reopened models did not load"
    yield app
    app.stop()


def call(app, path: str, body=None, *, raw: bytes | None = None, headers: dict | None = None,
         ) -> tuple[int, object]:
    """(status, decoded answer) of a request to the workspace: JSON, or bytes for the rest."""
    data, hdr = None, dict(headers or {})
    if body is not None:
        data = json.dumps(body).encode()
        hdr.setdefault("Content-Type", "application/json")
    elif raw is not None:
        data = raw
    req = urllib.request.Request(app.workspace.url.rstrip("/") + path, data=data, headers=hdr,
                                 method="POST" if data is not None else "GET")
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            status, ctype, payload = r.status, r.headers.get_content_type(), r.read()
    except urllib.error.HTTPError as err:
        status, ctype, payload = err.code, err.headers.get_content_type(), err.read()
    return status, json.loads(payload) if ctype == "application/json" else payload


def refused(app, status: int, path: str, body=None, **kw) -> str:
    """The one-line refusal of a request that must get `status`."""
    got, out = call(app, path, body, **kw)
    assert got == status, (got, out)
    line = out["error"]
    assert line and "\n" not in line and "Traceback" not in line
    return line


def observed_gcp(app, n: int = 2):
    """A GCP observed in >= n images (the tiny site's GCPs are), its id and first image."""
    g = next(g for g in app.session.gcps if len(g.observations) >= n)
    return g.id, sorted(g.observations)[0]


def test_the_state_names_every_gcp_and_its_pixels_as_the_viewer_computes_them(ws):
    status, st = call(ws, "/api/state")
    assert status == 200
    assert [g["id"] for g in st["gcps"]] == ws.session.ids
    assert [im["name"] for im in st["images"]] == list(ws.session.images)
    assert isinstance(st["version"], int) and st["model"] is True
    for entry, g in zip(st["gcps"], ws.session.gcps):
        assert entry["role"] == g.role and entry["enabled"] == g.enabled and entry["sigma_h_m"] == g.sigma_h_m
        res = residual_vectors(ws.models, g.observations)
        for im, (c, r) in g.observations.items():
            got = entry["images"][im]
            assert got["observed"] == pytest.approx([c, r], abs=1e-3)
            if im in res:
                assert got["residual_px"] == pytest.approx(math.hypot(*res[im]), abs=1e-3)
                assert got["predicted"] == pytest.approx([c - res[im][0], r - res[im][1]], abs=1e-3)
    # an observation removed (on the session, as the 3D viewer would): predicted there instead
    gid, image = observed_gcp(ws, 3)
    keep = ws.session.get(gid).observations[image]
    g = ws.session.get(gid)
    ws.call(lambda: (remove_observation(ws.session, gid, image), ws.gcp.changed()))
    try:
        pred = predict_unobserved(ws.models, g.observations, [image])[image]
        entry = next(e for e in call(ws, "/api/state")[1]["gcps"] if e["id"] == gid)
        assert entry["images"][image]["observed"] is None
        assert entry["images"][image]["predicted"] == pytest.approx([pred.col, pred.row], abs=1e-3)
    finally:
        ws.call(lambda: (undo(ws.session), ws.gcp.changed()))
    assert ws.session.get(gid).observations[image] == keep


def test_the_version_moves_with_every_edit_from_anywhere_and_only_then(ws):
    v0 = call(ws, "/api/version")[1]["version"]
    assert call(ws, "/api/version")[1]["version"] == v0
    gid, image = observed_gcp(ws)
    c, r = ws.session.get(gid).observations[image]
    ws.call(lambda: (add_observation(ws.session, gid, image, c + 1.0, r), ws.gcp.changed()))   # the 3D viewer's edit
    v1 = call(ws, "/api/version")[1]["version"]
    assert v1 > v0
    assert call(ws, "/api/state")[1]["version"] == v1
    ws.call(lambda: (undo(ws.session), ws.gcp.changed()))
    assert call(ws, "/api/version")[1]["version"] > v1


def test_observe_nudge_remove_undo_redo_change_the_session_exactly(ws):
    gid, image = observed_gcp(ws)
    before = ws.session.get(gid).observations[image]
    v = call(ws, "/api/version")[1]["version"]
    status, out = call(ws, "/api/observe", {"gcp": gid, "image": image, "col": 10.25, "row": 20.5, "version_seen": v})
    assert status == 200 and out["ok"] and out["stale"] is False and out["version"] > v
    assert ws.session.get(gid).observations[image] == (10.25, 20.5)
    assert read_gcps_geojson(ws.session.path)[ws.session.ids.index(gid)].observations[image] == pytest.approx((10.25, 20.5))
    assert f"image workspace: {gid} moved in {image}" in ws.gcp_panel.status.content      # the 3D viewer's panel says so
    for _ in range(3):
        assert call(ws, "/api/nudge", {"gcp": gid, "image": image, "dcol": 0.1, "drow": -1.0})[0] == 200
    assert ws.session.get(gid).observations[image] == pytest.approx((10.55, 17.5))
    assert call(ws, "/api/remove", {"gcp": gid, "image": image})[0] == 200
    assert image not in ws.session.get(gid).observations
    status, out = call(ws, "/api/undo", {})
    assert status == 200 and out["note"] == f"undone: remove {gid}'s observation in {image}"
    assert ws.session.get(gid).observations[image] == pytest.approx((10.55, 17.5))
    call(ws, "/api/undo", {})                           # the three nudges are one step
    assert ws.session.get(gid).observations[image] == (10.25, 20.5)
    call(ws, "/api/redo", {})
    assert ws.session.get(gid).observations[image] == pytest.approx((10.55, 17.5))
    call(ws, "/api/undo", {})
    call(ws, "/api/undo", {})
    assert ws.session.get(gid).observations[image] == before


def test_an_edit_of_a_gcp_or_observation_that_is_gone_is_refused_with_409(ws):
    gid, image = observed_gcp(ws)
    v = call(ws, "/api/version")[1]["version"]
    assert "no longer exists" in refused(ws, 409, "/api/observe", {"gcp": "GCP-XX", "image": image, "col": 1, "row": 1,
                                                                   "version_seen": v})
    ws.call(lambda: (delete_gcp(ws.session, gid), ws.gcp.changed()))         # deleted in another tab
    try:
        n = len(ws.session._undo)
        assert gid in refused(ws, 409, "/api/observe", {"gcp": gid, "image": image, "col": 1, "row": 1, "version_seen": v})
        assert gid in refused(ws, 409, "/api/nudge", {"gcp": gid, "image": image, "dcol": 0.1, "drow": 0})
        assert len(ws.session._undo) == n                # nothing recorded
    finally:
        ws.call(lambda: (undo(ws.session), ws.gcp.changed()))
    ws.call(lambda: (remove_observation(ws.session, gid, image), ws.gcp.changed()))
    try:
        assert "no observation" in refused(ws, 409, "/api/remove", {"gcp": gid, "image": image})
        assert "no observation" in refused(ws, 409, "/api/nudge", {"gcp": gid, "image": image, "dcol": 0, "drow": 1})
    finally:
        ws.call(lambda: (undo(ws.session), ws.gcp.changed()))


def test_bad_input_is_refused_with_400_and_one_line(ws):
    gid, image = observed_gcp(ws)
    w, h = ws.session.images[image]
    ok = {"gcp": gid, "image": image, "col": 5.0, "row": 5.0, "version_seen": 0}
    for change, words in [({"col": None}, "col"), ({"col": "abc"}, "not a number"), ({"col": True}, "not a number"),
                          ({"col": float("nan")}, "outside"), ({"col": w + 1.0}, "outside"), ({"row": -0.6}, "outside"),
                          ({"image": "nope.tif"}, "no image"), ({"gcp": ""}, "gcp"), ({"gcp": 3}, "gcp"),
                          ({"version_seen": 1.5}, "whole number"), ({"version_seen": 1 << 60}, "newer")]:
        assert words in refused(ws, 400, "/api/observe", {**ok, **change}), change
    assert "outside" in refused(ws, 400, "/api/nudge", {"gcp": gid, "image": image, "dcol": 1e6, "drow": 0})
    assert "JSON" in refused(ws, 400, "/api/observe", raw=b"gcp=1", headers={"Content-Type": "text/plain"})
    assert "JSON" in refused(ws, 400, "/api/observe", raw=b"{bad", headers={"Content-Type": "application/json"})
    assert "object" in refused(ws, 400, "/api/observe", raw=b"[1]", headers={"Content-Type": "application/json"})
    assert "X-Aerec-Workspace" in refused(ws, 400, "/api/import", raw=b"id\n")
    assert "level" in refused(ws, 400, f"/api/tile?image={image}&level=9&tx=0&ty=0")
    assert "outside" in refused(ws, 400, f"/api/tile?image={image}&level=0&tx=99&ty=0")
    assert "contrast" in refused(ws, 400, f"/api/tile?image={image}&level=0&tx=0&ty=0&contrast=0")
    refused(ws, 404, "/api/nothing")
    refused(ws, 404, "/static/../server.py")
    assert "localhost" in refused(ws, 403, "/api/version", headers={"Host": "evil.example:80"})


def test_tiles_are_read_by_windows_inside_the_image(ws, monkeypatch):
    image = sorted(ws.session.images)[0]
    w, h = ws.session.images[image]
    reads = []
    real = tiles_mod.read_window

    def spy(im, col0, row0, width, height, **kw):
        reads.append((col0, row0, width, height, kw.get("out_shape")))
        return real(im, col0, row0, width, height, **kw)
    monkeypatch.setattr(tiles_mod, "read_window", spy)
    ws.workspace.api.tiles = tiles_mod.TileSource(ws.images)          # empty caches
    n = tiles_mod.levels(w, h)
    for level in range(n):
        side = tiles_mod.TILE << level
        for ty in range(-(-h // side)):
            for tx in range(-(-w // side)):
                status, png = call(ws, f"/api/tile?image={image}&level={level}&tx={tx}&ty={ty}&contrast=1.5&gamma=1")
                assert status == 200
                px = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
                ww, hh = min(side, w - tx * side), min(side, h - ty * side)
                assert px.shape == (-(-hh // (1 << level)), -(-ww // (1 << level)))
    assert reads and all(0 <= c and 0 <= r and c + ww <= w and r + hh <= h for c, r, ww, hh, _ in reads)
    assert max(ww * hh for _, _, ww, hh, _ in reads) <= (tiles_mod.TILE << (n - 1)) ** 2
    k = len(reads)
    assert call(ws, f"/api/tile?image={image}&level=0&tx=0&ty=0&contrast=2")[0] == 200
    assert len(reads) == k                                # another contrast: the raw tile is cached


def test_markers_go_out_and_come_back_as_csv(ws):
    status, text = call(ws, "/api/export.csv")
    assert status == 200 and text.decode().startswith("id,role,")
    gid, image = observed_gcp(ws)
    before = ws.session.get(gid).observations[image]
    lines = text.decode().splitlines()
    head = lines[0].split(",")
    row = next(ln.split(",") for ln in lines[1:] if ln.split(",")[0] == gid and ln.split(",")[head.index("image")] == image)
    row[head.index("col")] = "12.5"
    status, out = call(ws, "/api/import?name=fix.csv", raw=(",".join(head) + "\n" + ",".join(row) + "\n").encode(),
                       headers={"X-Aerec-Workspace": "1"})
    assert status == 200 and out["updated"] == [gid]
    assert ws.session.get(gid).observations[image][0] == 12.5
    call(ws, "/api/undo", {})
    assert ws.session.get(gid).observations[image] == before
    assert "nothing imported" in refused(ws, 400, "/api/import?name=bad.csv", raw=(",".join(head) + "\n" + ",".join(
        row[:head.index("image")] + ["nope.tif"] + row[head.index("image") + 1:]) + "\n").encode(),
        headers={"X-Aerec-Workspace": "1"})


def test_the_gcp_tab_links_to_the_workspace_and_the_page_is_served(ws):
    assert ws.workspace.url in ws.gcp_panel.workspace_link.content
    assert "Open the image workspace" in ws.gcp_panel.workspace_link.content
    status, html = call(ws, "/")
    assert status == 200 and b"/static/workspace.js" in html
    for name in ("workspace.js", "workspace.css"):
        assert call(ws, f"/static/{name}")[0] == 200


def _saved_upgrade(app):
    """The upgrade the reopened run holds (OUT/upgrade), once the viewer has read it."""
    t0 = time.time()
    while app.saved_upgrade is None and time.time() - t0 < 60:
        time.sleep(0.1)
        app.wait_idle()
    up = app.call(app.gcp.upgrade_maps)
    assert up is not None, "the reopened run's upgrade was not read"
    return up


def test_a_gcp_with_no_observation_is_predicted_from_its_surveyed_position_once_upgraded(ws):
    """A new GCP, no observation yet: before an upgrade nothing predicts it; with the run's
    upgrade, its surveyed position predicts it in every image (the state table says "predicted
    from survey", the workspace's state carries the pixels, /api/predict, the GCP tab's Predict
    and its walk to the next image after a first observation give the same). A GCP
    placed in its images also gets, in each, where its surveyed position projects: beside its
    observation, within a pixel or two (the upgrade's error and the clicks' noise)."""
    from aerec_viewer.gcp_session import new_gcp
    from aerec_viewer.results import gcp_state_table
    from recon_core.euclidean.gcp_transfer import FROM_SURVEY

    up = _saved_upgrade(ws)
    images = list(ws.session.images)
    placed = next(g for g in ws.session.gcps if len(g.observations) >= 2)
    enu = up.frame.geodetic_to_enu(placed.llh[None])[0] + [2.0, -1.0, 0.0]      # 2 m east, 1 m south
    lon, lat, h = up.frame.enu_to_geodetic(enu[None])[0]
    assert predict_unobserved(ws.models, {}, images, None, (lon, lat, h)) == {}
    pred = predict_unobserved(ws.models, {}, images, up, (lon, lat, h))
    assert set(pred) == set(images) and all(p.source == FROM_SURVEY for p in pred.values())
    saved = ws.saved_upgrade
    ws.call(lambda: (new_gcp(ws.session, "G-NEW", x=lon, y=lat, h=h, role="check"), ws.gcp.changed()))
    try:
        # before an upgrade (none run, none read from OUT): no prediction anywhere
        ws.call(lambda: setattr(ws, "saved_upgrade", None))
        entry = next(e for e in call(ws, "/api/state")[1]["gcps"] if e["id"] == "G-NEW")
        assert entry["images"] == {}
        md = gcp_state_table(ws.session, ws.models, images, None)
        row = next(ln for ln in md.splitlines() if ln.startswith("| G-NEW |"))
        assert [c.strip() for c in row.strip("|").split("|")][2:] == ["-"] * len(images)
        assert "cannot predict G-NEW" in refused(ws, 409, f"/api/predict?gcp=G-NEW&image={images[0]}")
        # the run's upgrade: predicted from its surveyed position in every image
        ws.call(lambda: setattr(ws, "saved_upgrade", saved))
        st = call(ws, "/api/state")[1]
        entry = next(e for e in st["gcps"] if e["id"] == "G-NEW")
        assert set(entry["images"]) == set(images)
        for im, o in entry["images"].items():
            assert o["observed"] is None and o["source"] == "surveyed" and "surveyed position" in o["how"]
            assert o["predicted"] == pytest.approx([pred[im].col, pred[im].row], abs=1e-3)
            assert o["surveyed"] == o["predicted"]
        got = call(ws, f"/api/predict?gcp=G-NEW&image={images[0]}")[1]
        assert got["source"] == "surveyed" and (got["col"], got["row"]) == pytest.approx(
            (pred[images[0]].col, pred[images[0]].row), abs=1e-6)
        md = gcp_state_table(ws.session, ws.models, images, up)
        row = next(ln for ln in md.splitlines() if ln.startswith("| G-NEW |"))
        assert [c.strip() for c in row.strip("|").split("|")][2:] == ["predicted from survey"] * len(images)
        assert "*predicted from survey*: where its surveyed position projects" in md
        # the GCP tab: its state table, Predict, and after a first observation the walk on to
        # the next image, at the pixel its surveyed position gives there
        assert "| G-NEW | check | " + " | ".join(["predicted from survey"] * len(images)) in ws.g_state_table.content
        gp = ws.gcp_panel
        ws.call(lambda: gp.refresh(select="G-NEW"))
        ws.call(lambda: setattr(gp.image, "value", images[0]))
        ws.wait_idle()
        p = ws.call(gp._predict)
        assert p.source == FROM_SURVEY and (p.col, p.row) == pytest.approx((pred[images[0]].col, pred[images[0]].row))
        assert "surveyed position" in p.how and "upgrade" in p.uncertainty()
        ws.call(lambda: add_observation(ws.session, "G-NEW", images[0], p.col, p.row))
        assert ws.call(lambda: gp.walk_on("G-NEW")) == images[1]
        ws.wait_idle()
        assert gp.prediction is not None and gp.prediction[1].source == FROM_SURVEY
        assert (gp.prediction[1].col, gp.prediction[1].row) == pytest.approx((pred[images[1]].col, pred[images[1]].row))
        ws.call(lambda: (ws.picking.close_loupe(), gp.drop_prediction(), undo(ws.session), ws.gcp.changed()))
        # a placed GCP: its surveyed position's pixel beside each observation
        e = next(e for e in st["gcps"] if e["id"] == placed.id)
        gaps = [math.hypot(e["images"][im]["observed"][0] - e["images"][im]["surveyed"][0],
                           e["images"][im]["observed"][1] - e["images"][im]["surveyed"][1])
                for im in placed.observations]
        assert max(gaps) < 2.0, gaps
    finally:
        ws.call(lambda: setattr(ws, "saved_upgrade", saved))
        ws.call(lambda: (undo(ws.session), ws.gcp.changed()))
    assert "G-NEW" not in ws.session.ids


def test_a_refused_request_ends_its_connection(ws):
    """A request refused before its body is read (here: not JSON) closes the connection, so no
    body is ever read as a request of its own (a page elsewhere could smuggle an edit in a
    text/plain body); a POST that names another site as its origin is refused."""
    import http.client

    host, port = "127.0.0.1", ws.workspace.port
    inner = b'POST /api/undo HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\nContent-Length: 2\r\n\r\n{}'
    c = http.client.HTTPConnection(host, int(port), timeout=10)
    c.request("POST", "/api/undo", body=inner, headers={"Content-Type": "text/plain"})
    r = c.getresponse()
    assert r.status == 400 and r.getheader("Connection") == "close"
    r.read()
    c.close()
    c = http.client.HTTPConnection(host, int(port), timeout=10)
    c.request("POST", "/api/undo", body=b"{}", headers={"Content-Type": "application/json",
                                                         "Origin": "http://evil.example"})
    r = c.getresponse()
    assert r.status == 403 and b"own page" in r.read()
    c.close()


def test_the_frame_counter_reports_reach_the_rate_meter_and_bad_ones_are_400(ws):
    """The 3D page's counter iframe (framerate.py) posts its frame times; they land on the
    viewer's clock, the most recent one about now."""
    status, page = call(ws, "/static/frames.html?client=7")
    assert status == 200 and b"requestAnimationFrame" in page
    # framed by viser's page (its port, any host), where every other page is never framed
    with urllib.request.urlopen(ws.workspace.url + "static/frames.html?client=7", timeout=30) as r:
        assert r.headers.get("X-Frame-Options") is None
        assert r.headers.get("Content-Security-Policy") == (
            f"frame-ancestors http://*:{ws.port} https://*:{ws.port}")
    for page in ("", "static/workspace.js"):
        with urllib.request.urlopen(ws.workspace.url + page, timeout=30) as r:
            assert r.headers.get("X-Frame-Options") == "DENY"
            assert r.headers.get("Content-Security-Policy") == "frame-ancestors 'none'"
    t0 = time.monotonic()
    status, out = call(ws, "/api/frames", {"client": 7, "now": 5000.0, "frames": [4000.0, 4500.5, 5000]})
    assert status == 200 and out == {"frames": 3}
    got = list(ws.view_rate._frames[7])
    assert ws.view_rate.drawing(7, time.monotonic())
    assert abs(got[-1] - t0) < 1.0 and abs((got[-1] - got[0]) - 1.0) < 1e-9
    for body in ({"client": -1, "now": 1.0, "frames": []}, {"client": "x", "now": 1.0, "frames": []},
                 {"client": 1, "frames": []}, {"client": 1, "now": 10.0, "frames": "1,2"},
                 {"client": 1, "now": 10.0, "frames": [11.0]}, {"client": 1, "now": 10.0, "frames": [None]},
                 {"client": 1, "now": 1e6, "frames": list(range(6000))}):
        assert refused(ws, 400, "/api/frames", body)
    assert refused(ws, 400, "/api/frames", raw=b"client=1", headers={"Content-Type": "text/plain"})
    ws.view_rate.forget(7)


def test_a_restarted_viewer_answers_with_newer_versions_than_before(ws):
    """An open tab keeps the last version it saw: a viewer restarted behind it must not answer
    with older ones (the tab would ignore its state and send edits "from the future")."""
    from aerec_viewer.workspace.api import WorkspaceApi

    seen = call(ws, "/api/version")[1]["version"]
    time.sleep(0.01)
    again = WorkspaceApi(ws)                   # the API a new viewer process would start with
    assert again.version() > seen


def test_an_upgrade_fitted_on_a_replaced_model_predicts_nothing_there(ws):
    """A live run's bundle adjustment replaces a group's model (a new affine frame): the
    upgrade the page ran on the old one no longer maps it, so it predicts no pixel from a
    surveyed position there, and the Results tab says to upgrade again."""
    import copy as copy_

    from aerec_viewer.results import run_upgrade

    images = {im.name: im for im in ws.site.images}
    before = ws.gcp.upgrade, dict(ws.models)
    try:
        outcome = ws.call(lambda: run_upgrade(ws.session, ws.models, ws.cfg, images))
        ws.call(lambda: (setattr(ws.gcp, "upgrade", outcome), ws.gcp.update_upgrade_button()))
        maps = ws.call(ws.gcp.upgrade_maps)
        assert maps is not None and set(maps.maps) == set(outcome.maps) and outcome.maps
        assert "reconstruction changed" not in ws.g_ready.content
        # the worker replaces every model (as a global bundle adjustment does)
        ws.call(lambda: (ws.models.update({g: copy_.copy(m) for g, m in ws.models.items()}),
                         ws.gcp.update_upgrade_button()))
        assert ws.call(ws.gcp.upgrade_maps) is None
        assert "reconstruction changed since the last upgrade" in ws.g_ready.content
    finally:
        ws.call(lambda: (setattr(ws.gcp, "upgrade", before[0]), ws.models.clear(), ws.models.update(before[1]),
                         ws.gcp.update_upgrade_button()))
