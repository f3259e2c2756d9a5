"""The reconstruction worker: runs the pipeline in a thread and keeps the newest display state.

The worker never calls viser. The pipeline's events arrive synchronously on the pipeline's
thread (`ReconWorker.handle`); each one updates a `DisplayState` under a lock and bumps its
version. The viewer polls `snapshot()` (cheap: shallow copies of immutable parts) and applies
the newest state, at its own pace. Pausing makes `handle` wait, which pauses the pipeline.

Point clouds are kept as append-only batches per group and kind ("sparse", "dense"); a
`ModelUpdated` (the whole sparse model after a global bundle adjustment) starts a new
generation that replaces the sparse batches. Display decimation happens in the viewer; the
worker keeps every sparse point, and dense points up to `dense_cap` (thinned by a nested hash
subsample beyond; the full dense cloud is on disk).
"""

from __future__ import annotations

import json
import logging
import threading
import time
import traceback
from collections import deque
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from recon_core.errors import AerecError, InputError
from recon_core.events import (
    BundleAdjusted,
    EventBus,
    Message,
    ModelsReady,
    ModelUpdated,
    PointsAdded,
    StageDone,
    StageProgress,
    StageStarted,
    TileRegistered,
)
from recon_core.io.layout import OutLayout
from recon_core.io.models import load_model
from recon_core.io.ply import open_ply, ply_fields

from .display import (
    DisplayTransform,
    affine_display_transform,
    cloud_salt,
    keep_mask,
    refine_affine_transform,
)

log = logging.getLogger("aerec.viewer")
DENSE_CAP = 4_000_000       # dense points kept in memory per group (thinned beyond)


class Cancelled(BaseException):
    """Raised inside the pipeline's thread to stop it (BaseException: the EventBus only
    swallows Exception, so this one unwinds the pipeline)."""


@dataclass(frozen=True)
class PointBatch:
    """Points added by one event (immutable once stored)."""

    ids: np.ndarray          # (n,) int64
    xyz: np.ndarray          # (n, 3) float64, frame coordinates (affine)
    rgb: np.ndarray          # (n, 3) uint8
    n_views: np.ndarray      # (n,) float32
    reproj: np.ndarray       # (n,) float32
    t_added: float           # time.time() when the worker received it

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, m: np.ndarray | slice) -> "PointBatch":
        return PointBatch(self.ids[m], self.xyz[m], self.rgb[m], self.n_views[m], self.reproj[m],
                          self.t_added)


def concat_batches(batches: tuple[PointBatch, ...] | list[PointBatch]) -> PointBatch:
    """One batch holding all points of `batches` (t_added = the earliest)."""
    if not batches:
        z = np.zeros(0)
        return PointBatch(z.astype(np.int64), np.zeros((0, 3)), np.zeros((0, 3), np.uint8),
                          z.astype(np.float32), z.astype(np.float32), 0.0)
    if len(batches) == 1:
        return batches[0]
    return PointBatch(np.concatenate([b.ids for b in batches]),
                      np.concatenate([b.xyz for b in batches]),
                      np.concatenate([b.rgb for b in batches]),
                      np.concatenate([b.n_views for b in batches]),
                      np.concatenate([b.reproj for b in batches]),
                      min(b.t_added for b in batches))


@dataclass(frozen=True)
class CloudView:
    """Snapshot of one point store: its generation and batches (append-only within it)."""

    generation: int
    batches: tuple[PointBatch, ...]
    n: int
    kept_fraction: float = 1.0


class PointStore:
    """Append-only batches; `replace` starts a new generation."""

    def __init__(self, cap: int | None = None, salt: int = 0):
        self.batches: list[PointBatch] = []
        self.generation = 0
        self.n = 0
        self.cap = cap
        self.salt = salt
        self.kept_fraction = 1.0

    def append(self, batch: PointBatch) -> None:
        if self.kept_fraction < 1.0:
            batch = batch.subset(keep_mask(batch.ids, self.kept_fraction, self.salt))
        self.batches.append(batch)
        self.n += len(batch)
        while self.cap is not None and self.n > self.cap:
            self._thin()

    def replace(self, batch: PointBatch) -> None:
        self.batches = []
        self.n = 0
        self.generation += 1
        self.append(batch)

    def _thin(self) -> None:
        self.kept_fraction /= 2.0
        self.batches = [b.subset(keep_mask(b.ids, self.kept_fraction, self.salt)) for b in self.batches]
        self.n = sum(len(b) for b in self.batches)
        self.generation += 1

    def view(self) -> CloudView:
        return CloudView(self.generation, tuple(self.batches), self.n, self.kept_fraction)


@dataclass(frozen=True)
class TileView:
    """A registered tile as displayed."""

    tile_id: str
    image: str
    camera: np.ndarray        # (2, 4)
    footprint: np.ndarray     # (4, 3) affine frame
    order: int
    n_inliers: int
    t_registered: float
    version: int = 0


@dataclass
class GroupState:
    """Display state of one date group."""

    index: int
    tiles: dict[str, TileView] = field(default_factory=dict)
    newest_tile: str | None = None
    total_tiles: int = 0
    sparse: PointStore | None = None
    dense: PointStore | None = None
    ba: dict | None = None
    transform: DisplayTransform | None = None
    first_camera: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.sparse = self.sparse or PointStore(salt=cloud_salt(self.index, "sparse"))
        self.dense = self.dense or PointStore(cap=DENSE_CAP, salt=cloud_salt(self.index, "dense"))

    def stores(self) -> tuple[PointStore, PointStore]:
        """(sparse, dense): both made by __post_init__."""
        assert self.sparse is not None and self.dense is not None
        return self.sparse, self.dense


@dataclass(frozen=True)
class GroupSnapshot:
    index: int
    tiles: dict[str, TileView]
    newest_tile: str | None
    total_tiles: int
    sparse: CloudView
    dense: CloudView
    ba: dict | None
    transform: DisplayTransform | None


def failure_hint(exc: BaseException, stage: str | None) -> str:
    """One line on what to do after a failed run (shown under the error)."""
    where = f"the {stage} stage" if stage else "the run"
    if isinstance(exc, InputError):
        return "fix the input named above, then restart: finished stages are reused."
    if isinstance(exc, MemoryError):
        return (f"{where} ran out of memory: lower `dense.workers` or the tile size "
                "(aerec config --dump), then restart; finished stages are reused.")
    if isinstance(exc, (ImportError, OSError)) and ("lib" in str(exc) or isinstance(exc, ImportError)):
        return ("a library could not be loaded: reinstall with `python3 -m pip install -e .`; "
                "the terminal shows the traceback.")
    if isinstance(exc, AerecError):
        return f"{where} refused to go on (above); after a fix, restart to resume from it."
    return (f"{where} crashed: the terminal shows the traceback; `aerec run SITE OUT` resumes "
            f"from {where}, the stages before it are kept.")


@dataclass(frozen=True)
class DisplaySnapshot:
    """The newest display state, as the viewer reads it."""

    version: int
    status: str                 # starting, running, paused, done, reopened, failed, stopped
    error: str | None
    stage: str | None
    stage_done: int
    stage_total: int
    stage_message: str
    stage_group: int | None
    stages_finished: dict[str, float]
    groups: dict[int, GroupSnapshot]
    messages: tuple[tuple[str, str], ...]
    t_start: float
    t_first_points: float | None
    failed_stage: str | None = None    # the pipeline stage that was running when the run failed
    hint: str | None = None            # one line: what to do about the failure
    awaiting_gcps: bool = False        # the run stopped after the dense stage: not enough control GCPs yet

    @property
    def n_points(self) -> int:
        return sum(g.sparse.n + g.dense.n for g in self.groups.values())


class ReconWorker:
    """Runs (or reopens) a reconstruction in a background thread; keeps the display state.

    Args:
        site: site folder (None when reopening an OUT whose report names the site).
        out: output folder.
        cfg: pipeline configuration (recon_core.config.Config).
        mode: "run" runs the pipeline (resuming finished stages, whose saved models are
            replayed so their clouds show); "reopen" only loads what OUT holds.
        until: last stage to run (None: all).
    """

    def __init__(self, site: str | Path | None, out: str | Path, cfg=None, *, mode: str = "run",
                 until: str | None = None):
        if mode not in ("run", "reopen"):
            raise ValueError(f"mode must be 'run' or 'reopen', not {mode!r}")
        self.site = None if site is None else Path(site)
        self.out = Path(out)
        self.cfg = cfg
        self.mode = mode
        self.until = until
        self.redo_from: str | None = None   # set by rerun_from for the next run
        self.models: dict = {}          # group -> SparseModel once the sparse stage is done
        self.models_version = 0         # bumped whenever `models` changes
        self.report: dict = {}
        self._lock = threading.Lock()
        self._version = 0
        self._status = "starting"
        self._error: str | None = None
        self._running_stage: str | None = None
        self._failed_stage: str | None = None
        self._hint: str | None = None
        self._stage: tuple[str | None, int, int, str, int | None] = (None, 0, 0, "", None)
        self._finished: dict[str, float] = {}
        self._groups: dict[int, GroupState] = {}
        self._messages: deque[tuple[str, str]] = deque(maxlen=40)
        self._t_start = time.time()
        self._t_first_points: float | None = None
        self._awaiting_gcps = False
        self._resume_gate = threading.Event()
        self._resume_gate.set()
        self._cancel = False
        self._stopping = False
        self._thread: threading.Thread | None = None
        self.done = threading.Event()

    # -- control ------------------------------------------------------------------------------
    def start(self) -> "ReconWorker":
        self._thread = threading.Thread(target=self._main, name="aerec-worker", daemon=True)
        self._thread.start()
        return self

    def rerun_from(self, stage: str) -> str | None:
        """Run the pipeline again from `stage` (e.g. "upgrade" after the operator's upgrade:
        the same code and files as `aerec run --redo-from upgrade`). Returns None when started,
        else why not: "busy" while a run is still going (try again when it is done), or a
        sentence (no site, told to stop before that stage, the saved sparse model does not
        match this configuration and would be recomputed, the viewer is stopping)."""
        from recon_core import pipeline, resume
        from recon_core.config import Config
        from recon_core.io.site import load_site

        if self._stopping:
            return "the viewer is stopping"
        if not self.done.is_set():
            return "busy"
        if self.site is None:
            return "no site to run on"
        if self.until is not None and pipeline.STAGES.index(self.until) < pipeline.STAGES.index(stage):
            return f"this session stops after the {self.until} stage"
        before = pipeline.STAGES[: pipeline.STAGES.index(stage)]
        done = resume.finished_stages(self.out, self.cfg or Config(), load_site(self.site))
        if "sparse" in before and "sparse" not in done:
            return ("the saved sparse model does not match this configuration: re-running would "
                    "recompute it (and move the affine frame); run `aerec run` on this folder first")
        if self._thread is not None:
            self._thread.join()
        self.mode, self.redo_from = "run", stage
        self._cancel = False
        self._resume_gate.set()
        self.done.clear()
        self._set_status("starting")
        self.start()
        return None

    def pause(self) -> None:
        with self._lock:
            if self._status in ("running", "starting"):
                self._status = "paused"
                self._version += 1
        self._resume_gate.clear()

    def resume(self) -> None:
        with self._lock:
            if self._status == "paused":
                self._status = "running"
                self._version += 1
        self._resume_gate.set()

    @property
    def paused(self) -> bool:
        return not self._resume_gate.is_set()

    def stop(self, timeout: float = 5.0) -> None:
        """Ask the pipeline to stop at its next event and wait for the thread a little; no
        re-run starts after this."""
        self._stopping = True
        self._cancel = True
        self._resume_gate.set()
        if self._thread is not None:
            self._thread.join(timeout)

    def join(self, timeout: float | None = None) -> bool:
        return self.done.wait(timeout)

    # -- the listener ---------------------------------------------------------------------------
    def handle(self, ev: object) -> None:
        """EventBus listener: fold one event into the display state (pipeline thread)."""
        now = time.time()
        with self._lock:
            self._fold(ev, now)
            self._version += 1
        if isinstance(ev, ModelsReady):
            self.models = dict(ev.models)      # replaced whole: readers never see it change
            self.models_version += 1
        self._gate()

    def _gate(self) -> None:
        while not self._resume_gate.wait(0.2):
            if self._cancel:
                break
        if self._cancel:
            raise Cancelled()

    def _group(self, g: int) -> GroupState:
        if g not in self._groups:
            self._groups[g] = GroupState(g)
        return self._groups[g]

    def _fold(self, ev: object, now: float) -> None:
        if isinstance(ev, StageStarted):
            self._running_stage = ev.stage
            self._stage = (ev.stage, 0, 0, "started", None)
        elif isinstance(ev, StageProgress):
            self._stage = (ev.stage, int(ev.done), int(ev.total), ev.message, ev.group)
        elif isinstance(ev, StageDone):
            key = ev.stage if ev.group is None else f"{ev.stage} [g{ev.group}]"
            self._finished[key] = float(ev.seconds)
        elif isinstance(ev, TileRegistered):
            self._fold_tile(ev, now)
        elif isinstance(ev, PointsAdded):
            gs = self._group(ev.group)
            batch = _batch(ev.ids, ev.xyz, ev.rgb, ev.n_views, ev.reproj_px, now)
            sparse, dense = gs.stores()
            (dense if ev.kind == "dense" else sparse).append(batch)
            self._ensure_transform(gs, batch.xyz)
        elif isinstance(ev, ModelUpdated):
            self._fold_model(ev, now)
        elif isinstance(ev, BundleAdjusted):
            self._group(ev.group).ba = {"scope": ev.scope, "cost_before": ev.cost_before,
                                        "cost_after": ev.cost_after, "rms_px": ev.rms_px,
                                        "n_cameras": ev.n_cameras, "n_points": ev.n_points,
                                        "seconds": ev.seconds}
        elif isinstance(ev, Message):
            self._messages.append((ev.level, ev.text))
        elif isinstance(ev, ModelsReady):
            pass                                  # handled outside the lock (handle)
        else:                                     # an event type added later: show its name
            self._messages.append(("debug", f"event {type(ev).__name__}"))

    def _fold_tile(self, ev: TileRegistered, now: float) -> None:
        gs = self._group(ev.group)
        old = gs.tiles.get(ev.tile_id)
        gs.tiles[ev.tile_id] = TileView(ev.tile_id, ev.image, np.asarray(ev.camera, float),
                                        np.asarray(ev.footprint, float), int(ev.order),
                                        int(ev.n_inliers), now, 0 if old is None else old.version + 1)
        gs.newest_tile = ev.tile_id
        gs.total_tiles = int(ev.total_tiles)
        self._stage = ("sfm", len(gs.tiles), int(ev.total_tiles), f"registered {ev.tile_id}", ev.group)
        if gs.first_camera is None:
            gs.first_camera = np.asarray(ev.camera, float)

    def _fold_model(self, ev: ModelUpdated, now: float) -> None:
        gs = self._group(ev.group)
        for tid, fp in ev.footprints.items():
            t = gs.tiles.get(tid)
            if t is not None:
                gs.tiles[tid] = replace(t, camera=np.asarray(ev.cameras.get(tid, t.camera), float),
                                        footprint=np.asarray(fp, float), version=t.version + 1)
        batch = _batch(ev.ids, ev.xyz, ev.rgb, ev.n_views, ev.reproj_px, now)
        gs.stores()[0].replace(batch)
        if gs.transform is not None:
            gs.transform = refine_affine_transform(gs.transform, batch.xyz)
        self._ensure_transform(gs, batch.xyz)

    def _ensure_transform(self, gs: GroupState, xyz: np.ndarray) -> None:
        if len(xyz) and self._t_first_points is None:
            self._t_first_points = time.time()
        if gs.transform is None and len(xyz) >= 3:
            cam = gs.first_camera
            if cam is None:                       # points before any tile: identity-like camera
                cam = np.hstack([np.eye(3)[:2], np.zeros((2, 1))])
            gs.transform = affine_display_transform(xyz, cam)

    # -- reading --------------------------------------------------------------------------------
    @property
    def version(self) -> int:
        return self._version

    def snapshot(self) -> DisplaySnapshot:
        with self._lock:
            groups = {g: GroupSnapshot(g, dict(s.tiles), s.newest_tile, s.total_tiles,
                                       s.stores()[0].view(), s.stores()[1].view(),
                                       None if s.ba is None else dict(s.ba), s.transform)
                      for g, s in self._groups.items()}
            st = self._stage
            return DisplaySnapshot(self._version, self._status, self._error, st[0], st[1], st[2],
                                   st[3], st[4], dict(self._finished), groups,
                                   tuple(self._messages), self._t_start, self._t_first_points,
                                   self._failed_stage, self._hint, self._awaiting_gcps)

    def _set_status(self, status: str, error: str | None = None, hint: str | None = None) -> None:
        with self._lock:
            self._status = status
            self._error = error
            if status == "failed":
                self._failed_stage, self._hint = self._running_stage, hint
            elif status in ("starting", "running"):
                self._failed_stage = self._hint = None
            self._version += 1

    def message(self, text: str, level: str = "info") -> None:
        with self._lock:
            self._messages.append((level, text))
            self._version += 1

    # -- the thread -----------------------------------------------------------------------------
    def _main(self) -> None:
        self._running_stage = None             # a failure before any stage starts names none
        try:
            self._set_status("running" if self._resume_gate.is_set() else "paused")
            if self.mode == "reopen":
                self._reopen()
                self._set_status("reopened")
            else:
                self._run_pipeline()
                self._set_status("done")
        except Cancelled:
            self._set_status("stopped")
        except AerecError as exc:
            self._set_status("failed", str(exc), failure_hint(exc, self._running_stage))
        except Exception as exc:  # shown in the panel; the viewer stays up
            log.error("worker failed:\n%s", traceback.format_exc())
            self._set_status("failed", f"{type(exc).__name__}: {exc}",
                             failure_hint(exc, self._running_stage))
        finally:
            self.done.set()

    def _run_pipeline(self) -> None:
        from recon_core import pipeline, preflight, resume
        from recon_core.config import Config
        from recon_core.io.site import load_site

        cfg = self.cfg or Config()
        assert self.site is not None          # a run has its site (only a reopen may lack one)
        site = load_site(self.site)
        done = resume.finished_stages(self.out, cfg, site) if self.redo_from is None else set()
        if "sparse" not in done:              # what `aerec run` refuses before any compute
            preflight.check_config(cfg)
            preflight.check_images(site)
        if "sparse" in done:
            self._replay_saved(dense="dense" in done)
        until = self.until
        self._awaiting_gcps = False
        if (until is None or pipeline.STAGES.index(until) > pipeline.STAGES.index("dense")) \
                and not upgradable(site, self.out, cfg):
            # not enough control GCPs yet (a first demo, a site without a GCP file): the affine
            # reconstruction runs to the end, and the operator places them next
            until, self._awaiting_gcps = "dense", True
            self.message("not enough control GCPs observed in 2 images yet (4, or 3 when the images state "
                         "their viewing directions): the reconstruction stops after "
                         "the dense stage; place them in the GCP tab, then press Upgrade")
        state = pipeline.run(self.site, self.out, cfg, until=until,
                             bus=EventBus(self.handle), resume=True, redo_from=self.redo_from)
        self.models = dict(state.models)
        self.models_version += 1
        self.report = dict(state.report)

    def _reopen(self) -> None:
        lay = OutLayout(self.out)
        if lay.report.exists():
            self.report = json.loads(lay.report.read_text())
        self._replay_saved(dense=True)
        if not self.models:
            raise_missing(self.out)

    def _replay_saved(self, dense: bool) -> None:
        """Show the saved models (and dense clouds) of OUT as if they were being computed."""
        lay = OutLayout(self.out)
        for g in lay.model_groups():
            model = load_model(lay, g)
            self.models = {**self.models, g: model}
            self.models_version += 1
            replay_model(model, self.handle)
            n_dense = replay_dense(lay, g, self.handle) if dense else 0
            self.message(f"group {g}: loaded the saved model from {lay.group_dir(g)}"
                         + (f" ({n_dense} dense points)" if n_dense else ""))


def upgradable(site, out: Path, cfg) -> bool:
    """Does the working GCP set give some date group the control GCPs the upgrade needs?"""
    from recon_core import preflight
    from recon_core.io.gcps import read_gcps_geojson, working_gcp_file
    from recon_core.model.grouping import group_by_date

    path = working_gcp_file(site.root, out)
    try:
        gcps = read_gcps_geojson(path, {im.name: im for im in site.images}) if path.exists() else []
    except InputError:
        return True                           # let the run say what is wrong with the file
    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    return any(level in ("ok", "joint", "error") for level, _, _ in preflight.gcp_findings(groups, gcps, cfg))


def raise_missing(out: Path) -> None:
    raise InputError(out, "holds no saved model (affine/group_*/cameras.json): run the "
                          "reconstruction first (aerec view SITE or aerec run)")


def _batch(ids, xyz, rgb, n_views, reproj, t: float) -> PointBatch:
    n = len(ids)
    rgb = np.asarray(rgb, dtype=np.uint8).reshape(n, -1) if n else np.zeros((0, 3), np.uint8)
    if rgb.shape[1] == 1:
        rgb = np.repeat(rgb, 3, axis=1)
    return PointBatch(np.asarray(ids, dtype=np.int64), np.asarray(xyz, dtype=np.float64).reshape(n, 3),
                      rgb[:, :3], np.asarray(n_views, dtype=np.float32).reshape(n),
                      np.asarray(reproj, dtype=np.float32).reshape(n), t)


def replay_model(model, listener) -> None:
    """Feed a saved SparseModel to a listener as the events a live run would have emitted."""
    ids, n_img, rms = model.point_stats()
    g = model.gray[ids]
    total = len(model.tiles)
    order = list(model.register_order) or [int(t) for t in np.flatnonzero(model.registered)]
    fps = {}
    by_index = model.footprints(order)
    for k, t in enumerate(order):
        tile = model.tiles[t]
        fps[tile.id] = by_index[t]
        listener(TileRegistered(model.group, tile.id, tile.image, model.cams[t].copy(),
                                fps[tile.id], 0, k, total))
    cams = {model.tiles[t].id: model.cams[t].copy() for t in order}
    listener(ModelUpdated(model.group, cams, fps, ids, model.X[ids].copy(),
                          np.stack([g, g, g], 1), n_img, rms))


def replay_dense(out: OutLayout, g: int, listener, chunk: int = 2_000_000) -> int:
    """Feed a saved dense cloud to a listener by chunks (as dense PointsAdded events); its size."""
    path = out.dense_ply(g)
    if not path.exists():
        return 0
    rec = open_ply(path)
    for a in range(0, len(rec), chunk):
        xyz, rgb, extra = ply_fields(rec[a:a + chunk])
        assert rgb is not None              # the dense stage writes colours
        listener(PointsAdded(g, np.arange(a, a + len(xyz)), xyz, rgb, extra["n_views"].astype(np.int64),
                             extra["reproj_px"], kind="dense"))
    return len(rec)
