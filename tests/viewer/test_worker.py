"""The worker that folds the pipeline's events into the display state: growth, thinning, pause,
the point budget."""

from __future__ import annotations

import threading
import time

import numpy as np

from aerec_viewer.worker import ReconWorker
from recon_core.events import (
    BundleAdjusted,
    Message,
    ModelUpdated,
    PointsAdded,
    StageProgress,
    TileRegistered,
)


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


def test_an_empty_model_update_is_folded_without_error():
    """A joint reconstruction's update can hold no point of one group yet (its images not
    registered): the viewer folds it as an empty batch."""
    from aerec_viewer.worker import _batch

    b = _batch(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8), np.zeros(0), np.zeros(0), 0.0)
    assert b.xyz.shape == (0, 3) and b.rgb.shape == (0, 3)

