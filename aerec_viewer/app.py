"""The viewer application: viser server, layout, and the update thread.

Threads:
- the worker's thread runs the pipeline (worker.py) and never calls viser;
- viser's own threads run GUI and click callbacks: they only `submit` commands;
- one update thread (`ViewerApp._loop`) executes the queued commands in order and applies the
  newest worker snapshot inside `server.atomic()`, at most `update_hz` times a second. It is
  the only code that changes scene nodes and panel contents, so no viser state needs a lock.

The scene and the GUI are server-wide (not per client): every browser tab sees the same state.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
import traceback
from collections import deque
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from recon_core.context import UpgradeMaps
from recon_core.errors import AerecError

from .display import (
    DisplayTransform,
    euclidean_display_transform,
    image_footprint,
)
from .framerate import ViewRateMeter
from .gcp_controller import GcpController
from .gcp_marks import GcpMarks
from .gcp_panel import GcpPanel
from .gcp_session import GcpError, open_session
from .imagery import ImageSource
from .motion import MotionDisplay
from .picking import PickingView
from .recon_panel import ReconstructionPanel
from .results import DsmPanel
from .scene import SceneView, tile_windows_for
from .views import ClientViews
from .worker import DisplaySnapshot, ReconWorker
from .workspace import WorkspaceServer

if TYPE_CHECKING:
    from recon_core.euclidean.ground_reference import GroundReference

log = logging.getLogger("aerec.viewer")

class _OneLine(logging.Filter):
    """A client's malformed handshake or frame is the client's problem: one line on the console,
    not a traceback (the server goes on either way)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            record.msg = f"{record.getMessage()}: {type(record.exc_info[1]).__name__}: {record.exc_info[1]}"
            record.args, record.exc_info, record.exc_text = (), None, None
        return True


def quiet_protocol_errors() -> None:
    for name in ("websockets.server", "websockets.asyncio.server", "websockets.protocol"):
        lg = logging.getLogger(name)
        if not any(isinstance(f, _OneLine) for f in lg.filters):
            lg.addFilter(_OneLine())


class ViewerApp:
    """The AE-Rec viewer around one reconstruction.

    Args:
        out: output folder (created if needed).
        site: site folder; None when reopening an OUT whose report.json names its site.
        cfg: pipeline configuration (recon_core.config.Config); None: the report's (reopen)
            or the defaults.
        mode: "run" (run or resume the pipeline) or "reopen" (show what OUT holds, compute
            nothing).
        host, port: where to serve (port 0: any free port; a busy port moves to the next one,
            so read `port` after construction).
        update_hz: scene updates per second at most.
        workspace_port: the image workspace's port (default: the one after viser's, or any
            free one when viser's is; a busy one moves to the next).
    """

    def __init__(self, out: str | Path, site: str | Path | None = None, cfg=None, *,
                 mode: str = "run", host: str = "127.0.0.1", port: int = 8080,
                 update_hz: float = 4.0, until: str | None = None, budget: int | None = None,
                 reference: GroundReference | None = None, workspace_port: int | None = None):
        import viser

        from recon_core.config import Config, config_from_dict
        from recon_core.io.site import load_site

        self.out = Path(out)
        self.mode = mode
        report = _read_report(self.out)
        if site is None:
            site = _site_from_report(self.out, report)
        if cfg is None:
            skipped: list[str] = []
            cfg = config_from_dict(report["config"], unknown=skipped) if report.get("config") else Config()
            if skipped:
                log.warning("%s names parameters this version does not know (ignored): %s",
                            self.out / "report.json", ", ".join(skipped))
        self.cfg = cfg
        self.site = load_site(Path(site).resolve())
        self.out.mkdir(parents=True, exist_ok=True)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.scene.set_up_direction("+z")
        # everything drawn is unlit (points, images, lines, labels): viser's default lights cast
        # shadows in 3 cascades, 3 more passes over the scene per frame, and its environment map
        # is fetched and prefiltered at start; without a GPU both cost frames (docs/viewer.md)
        self.server.scene.configure_default_lights(enabled=False, cast_shadow=False)
        self.server.scene.configure_environment_map(hdri=None)
        self.server.gui.configure_theme(control_width="large", dark_mode=False)
        self.worker = ReconWorker(self.site.root, self.out, cfg, mode=mode, until=until)
        self.reference = reference        # euclidean.ground_reference.GroundReference, or None
        self.images = ImageSource(self.site.images, extra=[reference.ortho] if reference else ())
        self.scene = SceneView(self.server, self.images,
                               tile_windows_for(self.site.images, cfg.tiling.tile_size,
                                                cfg.tiling.overlap))
        if budget is not None:
            self.scene.settings.budget = int(budget)
        self.view_rate = ViewRateMeter()
        self.motion = MotionDisplay(self)
        self.session = open_session(self.out, self.site)
        self.models: dict = {}
        self._models_version = 0
        self.frame = "affine"
        self.update_hz = update_hz
        self._euclid: dict[int, DisplayTransform | None] = {}
        self.saved_upgrade: UpgradeMaps | None = None   # the upgrade OUT holds, once a run is done
        self._auto_frame_tried = False
        self._shifted: dict = {}
        self._offsets: dict[int, float] = {}
        self._queue: queue.Queue = queue.Queue()
        self.tick_log: deque = deque(maxlen=100_000)   # (start, seconds, points sent)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seen_version = -1
        self._framed = False
        self.gcp = GcpController(self)       # the clicks, the working set's edits, the upgrade
        # the image workspace (its own page and port): bound now, so the GCP tab can link to it
        self.workspace = WorkspaceServer(self, host, (0 if port == 0 else self.port + 1)
                                         if workspace_port is None else workspace_port,
                                         viewer_port=self.port)
        self.picking = PickingView(self)     # the picking plane and its loupe (/gcp/plane)
        self.marks = GcpMarks(self)          # every other /gcp node
        self._gui_cache: dict[int, object] = {}   # id(handle) -> the content it shows
        self._build_gui()
        self.views = ClientViews(self)       # each tab's camera: framing, zoom at the cursor, the drag guard

    # -- lifecycle ------------------------------------------------------------------------------
    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        host = "127.0.0.1" if host in ("0.0.0.0", "") else host
        return f"http://{host}:{self.port}"

    def start(self) -> "ViewerApp":
        quiet_protocol_errors()
        # warm the shared tone curve (reads every image's overview) before the first tiles
        threading.Thread(target=lambda: self.images.tone, name="aerec-tone", daemon=True).start()
        self.worker.start()
        self._thread = threading.Thread(target=self._loop, name="aerec-viewer", daemon=True)
        self._thread.start()
        self.workspace.start()
        return self

    def stop(self) -> None:
        self.gcp.dsm_rerun_pending = False
        self._stop.set()
        self.worker.stop(timeout=2.0)
        self._wake.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.workspace.stop()
        self.server.stop()

    def submit(self, fn: Callable[[], object]) -> Future:
        """Queue work for the update thread (what every GUI callback does)."""
        fut: Future = Future()
        self._queue.put((fn, fut))
        self._wake.set()
        return fut

    def call(self, fn: Callable[[], object], timeout: float = 30.0):
        """Run fn on the update thread and return its result. Past `timeout` the work is
        withdrawn if it has not started (TimeoutError): a caller told "busy" may retry without
        the first try also running later."""
        fut = self.submit(fn)
        try:
            return fut.result(timeout)
        except FutureTimeout:
            fut.cancel()
            raise

    def wait_idle(self, timeout: float = 10.0) -> None:
        """Return once the newest worker state has been applied."""
        self.call(lambda: None, timeout)
        self.call(self._tick, timeout)

    def _loop(self) -> None:
        period = 1.0 / self.update_hz
        while not self._stop.is_set():
            t0 = time.time()
            self._drain()
            try:
                sent = self._tick()
            except Exception:
                sent = -1
                log.error("viewer update failed:\n%s", traceback.format_exc())
            self.tick_log.append((t0, time.time() - t0, sent))
            self._wake.wait(max(0.0, period - (time.time() - t0)))
            self._wake.clear()
        self._drain()

    def _drain(self) -> None:
        while True:
            try:
                fn, fut = self._queue.get_nowait()
            except queue.Empty:
                return
            if not fut.set_running_or_notify_cancel():
                continue                       # withdrawn by a caller that gave up waiting
            try:
                fut.set_result(fn())
            except (AerecError, GcpError) as exc:
                self.note(str(exc), "error")
                fut.set_exception(exc)
            except Exception as exc:
                log.error("viewer command failed:\n%s", traceback.format_exc())
                self.note(f"{type(exc).__name__}: {exc}", "error")
                fut.set_exception(exc)

    # -- the update -----------------------------------------------------------------------------
    def _tick(self) -> int | None:
        """Apply the newest worker state; returns the number of points sent (None: no change)."""
        self.motion.tick()
        snap = self.worker.snapshot()
        if snap.status in ("done", "reopened") and not self._auto_frame_tried:
            # a finished run that holds an upgrade opens in metres (the affine frame "may be
            # depth-reversed": a skewed slab), once; the Frame dropdown goes back
            self._auto_frame_tried = True
            if not self._euclid and self._load_saved_upgrade():
                self.note("showing the Euclidean frame (metres, from OUT/upgrade/); Frame in the "
                          "Results tab switches to the affine one")
                self.set_frame("euclidean")
                return None
        if self.worker.models_version != self._models_version:
            self._models_version = self.worker.models_version
            self.models = dict(self.worker.models)
            self.marks.invalidate()
            self.gcp_panel.relabel()          # "images placed n/N" counts registered images
            self.gcp_panel.listing.content = self.gcp_panel.working_set_table()   # residuals need the models
            self.gcp.update_upgrade_button()
        if self.gcp.dsm_rerun_pending and self.worker.done.is_set():
            self.gcp.start_dsm_rerun()
        if snap.version == self._seen_version and self.marks.key is not None:
            return None
        self._seen_version = snap.version
        with self.server.atomic():
            sent = self.scene.sync(snap, self.transforms(snap))
            if snap.status in ("done", "reopened"):
                self.scene.finish()
            self.recon.update(snap)
            self.gcp.update_upgrade_button()
            self.picking.relayout()
            if sent and not self._framed:
                self._framed = True
                if self.picking.plane is None:
                    self.picking.reframe = True
                    self.picking.show()
                for client in self.server.get_clients().values():
                    self.views.frame_client(client)
            self.marks.draw()
            self.dsm_panel.refresh(snap)
        return sent


    def transforms(self, snap: DisplaySnapshot) -> dict[int, DisplayTransform | None]:
        """The display transform of each group in the current frame.

        Euclidean: every upgraded group in the shared ENU frame. Affine: each group's own frame;
        groups after the first are shifted east, side by side (their frames are unrelated)."""
        if self.frame == "euclidean":
            return {g: self._euclid.get(g) for g in snap.groups}
        out = {}
        for g, gs in sorted(snap.groups.items()):
            T = gs.transform
            if T is None:
                out[g] = None
                continue
            dx = self._group_offset(g, snap)
            if dx == 0.0:
                out[g] = T
                continue
            key = (g, id(T))
            if key not in self._shifted:
                self._shifted = {k: v for k, v in self._shifted.items() if k[0] != g}
                self._shifted[key] = replace(T, b=T.b + np.array([dx, 0.0, 0.0]),
                                             label=T.label)
            out[g] = self._shifted[key]
        return out

    def _group_offset(self, g: int, snap: DisplaySnapshot) -> float:
        """East shift of group g's affine display: the widths of the groups before it + gaps."""
        if g in self._offsets:
            return self._offsets[g]
        x = 0.0
        for h in sorted(snap.groups):
            if h >= g:
                break
            lo, hi = self._group_extent(h, snap)
            x += (hi - lo) * 1.15
        if g > 0 and x == 0.0:
            return 0.0                         # the earlier groups have no extent yet
        lo, hi = self._group_extent(g, snap)
        self._offsets[g] = x - lo if g > 0 else 0.0
        return self._offsets[g]

    def _group_extent(self, g: int, snap: DisplaySnapshot) -> tuple[float, float]:
        """x range of group g's first image footprint in its own affine display."""
        gs = snap.groups.get(g)
        first = None if gs is None else min(gs.tiles.values(), key=lambda t: t.order, default=None)
        if gs is None or gs.transform is None or first is None:
            return 0.0, 0.0
        im = self.images.images.get(first.image)
        assert im is not None                # a tile's image is one of the site's
        fp = image_footprint(gs.transform, first.camera, im.width, im.height)
        return float(fp[:, 0].min()), float(fp[:, 0].max())

    # -- panel ----------------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        tabs = gui.add_tab_group()
        with tabs.add_tab("Reconstruction"):
            self.recon = ReconstructionPanel(self, gui)
        with tabs.add_tab("GCPs"):
            self.gcp_panel = GcpPanel(self, gui)
        with tabs.add_tab("Results"):
            self.g_upgrade = gui.add_button("Upgrade to Euclidean", disabled=True)
            self.g_ready = gui.add_markdown("")
            self.g_allow_flat = gui.add_checkbox(
                "Accept GCPs nearly on one plane", self.cfg.upgrade.allow_flat_gcps,
                hint="the upgrade then goes on where it would refuse control GCPs that cannot fix the "
                     "height scale (the images state no viewing angles): its expected height error is "
                     "said with the result (upgrade.allow_flat_gcps)")
            with gui.add_folder("GCP placement", expand_by_default=False):
                self.g_ready_list = gui.add_markdown("")
                self.g_state_table = gui.add_markdown("")
            self.g_frame_sel = gui.add_dropdown("Frame", ["affine", "Euclidean"],
                                                initial_value="affine", disabled=True)
            self.g_upgrade_md = gui.add_markdown("")
            self.dsm_panel = DsmPanel(self, gui)
        self._wire()
        # the list opens on the first GCP still to place (N from there goes on), not on "new"
        gp = self.gcp_panel
        gp.refresh(select=gp.neighbour(None, +1)[0] if self.session.ids else "keep")
        self.picking.set_regions()

    def _wire(self) -> None:
        sub = self.submit

        def setter(fn):
            def callback(_) -> None:
                sub(fn)
            return callback

        self.g_upgrade.on_click(setter(self.gcp.do_upgrade))
        self.g_allow_flat.on_update(setter(lambda: self.gcp.allow_flat(bool(self.g_allow_flat.value))))
        self.g_frame_sel.on_update(setter(lambda: self.set_frame(
            "euclidean" if self.g_frame_sel.value == "Euclidean" else "affine")))

    def force(self) -> None:
        self._seen_version = -1

    def set_md(self, handle, text: str) -> None:
        key = id(handle)
        if self._gui_cache.get(key) != text:
            self._gui_cache[key] = text
            handle.content = text


    def note(self, text: str, level: str = "info") -> None:
        """Show a one-line status in the GCP tab and in the messages list."""
        self.gcp_panel.status.content = f"**{level}:** {text}" if level != "info" else text
        self.worker.message(text, level)

    # -- cameras --------------------------------------------------------------------------------
    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Bounds of the displayed cloud joined with the ground each group's first image covers
        (so the view and the picking plane fit the whole site while the cloud still grows)."""
        b = self.scene.bounds()
        if b is None:
            return None
        lo, hi = (np.asarray(v, dtype=np.float64) for v in b)
        snap = self.worker.snapshot()
        for g, T in self.transforms(snap).items():
            tiles = snap.groups[g].tiles
            first = min(tiles.values(), key=lambda t: t.order, default=None)
            if T is None or first is None or first.image not in self.images.images:
                continue
            im = self.images.images[first.image]
            try:
                fp = image_footprint(T, first.camera, im.width, im.height, z=float(lo[2]))
            except np.linalg.LinAlgError:
                continue
            lo[:2] = np.minimum(lo[:2], fp[:, :2].min(axis=0))
            hi[:2] = np.maximum(hi[:2], fp[:, :2].max(axis=0))
        return lo, hi


    def _load_saved_upgrade(self) -> bool:
        """The display transforms of the upgrade OUT holds (OUT/upgrade/), if any."""
        from recon_core.io.models import load_upgrade

        try:
            saved = load_upgrade(self.out)
        except (OSError, ValueError, KeyError):
            return False
        if not saved or not saved[0]:
            return False
        maps, frame = saved
        self.saved_upgrade = UpgradeMaps(maps, frame)
        self._euclid = {g: euclidean_display_transform(m.H, frame.origin_llh, m.warp, m.enu_warp)
                        for g, m in maps.items()}
        self.g_frame_sel.disabled = False
        return True

    def set_frame(self, frame: str) -> None:
        if frame == "euclidean" and not self._euclid:
            frame = "affine"
        want = "Euclidean" if frame == "euclidean" else "affine"
        if self.g_frame_sel.value != want:
            self.g_frame_sel.value = want
        if frame == self.frame:
            return
        self.frame = frame
        self.scene.clear()
        self.force()
        self._framed = False
        self.marks.invalidate()
        self.picking.reset_layout()
        self._tick()
        self.dsm_panel.frame_changed()


def _read_report(out: Path) -> dict:
    import json

    p = out / "report.json"
    if not p.exists():
        return {}
    try:
        return json.loads(p.read_text())
    except ValueError:
        return {}


def _site_from_report(out: Path, report: dict) -> Path:
    from recon_core.errors import InputError

    site = report.get("site")
    if not site:
        raise InputError(out / "report.json", "names no site; pass the site folder with --site")
    for cand in (Path(site), out.parent / site, out / site):   # relative paths: try near OUT
        if cand.is_dir():
            return cand
    if not Path(site).is_dir():
        raise InputError(Path(site), f"the site named by {out / 'report.json'} is not there; "
                                     "pass the site folder with --site")
    return Path(site)
