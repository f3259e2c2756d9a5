"""What the workspace's endpoints do to the viewer: read its state, and edit the working GCP set
the way the GCP tab does.

Every edit runs on the viewer's update thread (ViewerApp.call), the one thread that runs the GCP
tab's edits too: that is what serialises edits (the session has no lock of its own), and it
makes the edit, its save to OUT/gcps.geojson (gcp_session) and the refresh of the 3D view and
the panel (GcpController.changed) one step that no other edit interleaves with. Each edit names
its GCP and its image; one whose GCP (or observation) no longer exists is refused with a
Conflict, never applied to whatever is selected elsewhere.
"""

from __future__ import annotations

import concurrent.futures
import copy
import json
import math
import threading
import time
from typing import TYPE_CHECKING, Callable

from ..gcp_session import (
    GcpError,
    add_observation,
    can_redo,
    can_undo,
    nudge_observation,
    remove_observation,
)
from ..results import gcps_key
from .state import Snapshot, workspace_state
from .tiles import TileSource

if TYPE_CHECKING:
    from ..app import ViewerApp

MAX_FRAMES = 5000          # frame times in one report of the counter iframe
EDIT_TIMEOUT_S = 20.0       # an edit waits this long for the update thread (an upgrade runs there)


class ApiError(Exception):
    """A refused request: its HTTP status (400 bad input, 404 unknown, 409 the state changed)
    and one line for the page."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status
        self.message = message


def bad(message: str) -> ApiError:
    return ApiError(400, message)


def conflict(message: str) -> ApiError:
    return ApiError(409, message)


class WorkspaceApi:
    """The workspace's operations on one ViewerApp."""

    def __init__(self, app: "ViewerApp"):
        self.app = app
        self.tiles = TileSource(app.images)
        self._lock = threading.Lock()
        self._key: tuple | None = None
        self._upgrade: tuple = (None, None)     # (the page's last upgrade, OUT's) the version saw
        # versions start from the boot's time in ms: a viewer restarted behind an open tab
        # answers with newer versions than any it gave before (a counter from 0 would look older
        # to the tab, which would then ignore every state and send edits "from the future")
        self._version = int(time.time() * 1000)
        self._state: tuple[int, bytes] | None = None      # (version, state JSON)

    # -- the 3D page's frame counter (framerate.py) ------------------------------------------------
    def frames(self, client: int, now_ms: float, frames_ms: object) -> dict:
        """A tab's counter iframe drew frames at `frames_ms` (its performance.now(), ms) and sent
        them at `now_ms`: they reach the viewer's rate meter on this process's clock."""
        if not isinstance(frames_ms, list) or len(frames_ms) > MAX_FRAMES:
            raise bad(f"frames: give a list of at most {MAX_FRAMES} times (ms)")
        if any(isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t)
               or not 0 <= t <= now_ms for t in frames_ms):
            raise bad("frames: each a time in ms, between 0 and now")
        recv = time.monotonic()
        self.app.view_rate.frames(client, [recv - (now_ms - t) / 1000.0 for t in frames_ms], recv)
        return {"frames": len(frames_ms)}

    # -- reading --------------------------------------------------------------------------------
    def version(self) -> int:
        """A counter that grows whenever what the page shows may have changed: the GCP set (any
        edit, undo, redo, from any tab or the 3D viewer), the models (new predictions) or the
        upgrade (new errors in metres, new predictions from the surveyed positions): the one the
        page ran or the one OUT holds. Cheap: the page polls it."""
        app = self.app
        key = (app.session.version, app._models_version)
        up = (app.gcp.upgrade, app.saved_upgrade)
        with self._lock:
            if key != self._key or any(a is not b for a, b in zip(up, self._upgrade)):
                self._key, self._upgrade = key, up
                self._version += 1
            return self._version

    def snapshot(self) -> Snapshot:
        """A copy of the working set and what it is shown with, taken on the update thread."""
        app = self.app

        def take() -> Snapshot:
            s = app.session
            up = app.gcp.upgrade
            return Snapshot(self.version(), copy.deepcopy(s.gcps), dict(s.images),
                            app.gcp_panel._registered_images(), dict(app.models), up, app.gcp.upgrade_maps(),
                            up is not None and up.gcps_key != gcps_key(s), can_undo(s), can_redo(s),
                            app.site.name)
        return self.on_update_thread(take)

    def state_json(self) -> bytes:
        """The state as JSON bytes, computed once per version (every tab polls the same)."""
        v = self.version()
        with self._lock:
            if self._state is not None and self._state[0] == v:
                return self._state[1]
        snap = self.snapshot()
        body = json.dumps(workspace_state(snap), allow_nan=False).encode()
        with self._lock:
            if self._state is None or self._state[0] <= snap.version:
                self._state = (snap.version, body)
        return body

    def predict(self, gcp: str, image: str) -> dict:
        """The GCP's pixel in `image` as the GCP tab's Predict gives it (results.predict_in): from
        its other observations and refined by matching, or from its surveyed position once the
        image's group is upgraded and it has fewer than 2 observations there; slower than the
        state's geometric prediction, asked for one image at a time."""
        from ..results import image_group, predict_in

        self.check_image(image)
        g = self.on_update_thread(lambda: copy.deepcopy(self.existing(gcp)))
        if image_group(self.app.models, image) is None:
            raise conflict(f"no registered model holds {image} yet (wait for the sparse stage)")
        pred = predict_in(self.app.models, image, g.observations, g.llh, self.app.gcp.upgrade_maps(),
                          {im.name: im for im in self.app.site.images})
        if pred is None:
            raise conflict(f"cannot predict {gcp} in {image}: observe it in another image of its "
                           "date group first")
        return {"gcp": gcp, "image": image, "col": pred.col, "row": pred.row, "how": pred.how,
                "uncertainty": pred.uncertainty(), "source": pred.source}

    def tile(self, image: str, level: int, tx: int, ty: int, **stretch) -> bytes:
        self.check_image(image)
        try:
            return self.tiles.encoded(image, level, tx, ty, **stretch)
        except ValueError as exc:
            raise bad(str(exc)) from None

    # -- checks ---------------------------------------------------------------------------------
    def check_image(self, image: str) -> tuple[int, int]:
        """(width, height) of a site image; 400 for a name the site does not have."""
        size = self.app.session.images.get(image)
        if size is None:
            raise bad(f"no image {image!r} in the site")
        return size

    def check_pixel(self, image: str, col: float, row: float) -> None:
        """400 unless (col, row) lies in the image (pixel centres 0 .. size - 1, edges +-0.5)."""
        w, h = self.check_image(image)
        if not (-0.5 <= col <= w - 0.5 and -0.5 <= row <= h - 0.5):
            raise bad(f"pixel (col {col:.2f}, row {row:.2f}) lies outside {image} ({w} x {h})")

    def existing(self, gcp: str):
        """The GCP (update thread); 409 when it is gone (deleted or renamed elsewhere)."""
        if gcp not in self.app.session.ids:
            raise conflict(f"{gcp} no longer exists (deleted or renamed in another tab or in the "
                           "3D viewer): choose a GCP in the list")
        return self.app.session.get(gcp)

    def observed(self, gcp: str, image: str) -> tuple[float, float]:
        """The GCP's observation in `image` (update thread); 409 when there is none any more."""
        ob = self.existing(gcp).observations.get(image)
        if ob is None:
            raise conflict(f"{gcp} has no observation in {image} (removed in another tab?): "
                           "click its pixel to place it")
        return ob

    # -- edits ----------------------------------------------------------------------------------
    def on_update_thread(self, fn: Callable[[], object]):
        """Run fn on the viewer's update thread and return its result; a refusal (ApiError, or
        a GcpError the session raised: 409) comes back as an ApiError, not as an error note in
        the 3D viewer's panel."""
        def guarded():
            try:
                return fn(), None
            except (ApiError, GcpError) as exc:
                return None, exc
        try:
            result, exc = self.app.call(guarded, timeout=EDIT_TIMEOUT_S)
        except concurrent.futures.TimeoutError:
            raise ApiError(503, "the viewer is busy (an upgrade running?): try again in a moment") from None
        if isinstance(exc, GcpError):
            raise conflict(str(exc))
        if exc is not None:
            raise exc
        return result

    def edit(self, fn: Callable[[], str]) -> dict:
        """Run an edit on the update thread; it returns its note, said in the 3D viewer's panel
        too (which it refreshes, with the markers, as the GCP tab's own edits do)."""
        def run() -> str:
            note = fn()
            self.app.gcp.changed(select="keep", note=f"image workspace: {note}")
            return note
        note = self.on_update_thread(run)
        return {"ok": True, "note": note, "version": self.version()}

    def observe(self, gcp: str, image: str, col: float, row: float, version_seen: int) -> dict:
        """Place (or move) the GCP's observation in the image at (col, row); `version_seen`: the
        state version the page showed when clicked (the answer says when it was stale)."""
        self.check_pixel(image, col, row)
        if version_seen > self.version():
            raise bad(f"version_seen {version_seen} is newer than the state ({self.version()})")

        before: list[int] = []

        def run() -> str:
            before.append(self.version())
            had = image in self.existing(gcp).observations
            add_observation(self.app.session, gcp, image, col, row)
            return f"{gcp} {'moved' if had else 'observed'} in {image} at col {col:.2f}, row {row:.2f}"
        out = self.edit(run)
        out["stale"] = version_seen < before[0]      # the page had not seen every change yet
        return out

    def nudge(self, gcp: str, image: str, dcol: float, drow: float) -> dict:
        """Move the GCP's observation in the image by (dcol, drow) px (nudges in a row: one Undo)."""
        self.check_image(image)

        def run() -> str:
            c, r = self.observed(gcp, image)
            self.check_pixel(image, c + dcol, r + drow)
            c, r = nudge_observation(self.app.session, gcp, image, dcol, drow)
            return f"{gcp} in {image} nudged to col {c:.2f}, row {r:.2f}"
        return self.edit(run)

    def remove(self, gcp: str, image: str) -> dict:
        self.check_image(image)

        def run() -> str:
            self.observed(gcp, image)
            remove_observation(self.app.session, gcp, image)
            return f"{gcp}'s observation in {image} removed"
        return self.edit(run)

    def undo(self) -> dict:
        """Undo the latest edit of the working set, whoever made it (the history is shared)."""
        return self.on_update_thread(lambda: {"ok": True, "note": f"undone: {self.app.gcp_panel._undo()}",
                                              "version": self.version()})

    def redo(self) -> dict:
        return self.on_update_thread(lambda: {"ok": True, "note": f"redone: {self.app.gcp_panel._redo()}",
                                              "version": self.version()})

    def import_csv(self, name: str, content: bytes) -> dict:
        """A marker CSV into the working set (the GCP tab's Import markers: one Undo)."""
        def run() -> dict:
            try:
                added, updated = self.app.gcp_panel.import_markers(name, content)
            except GcpError as exc:
                raise bad(str(exc)) from None
            return {"ok": True, "added": added, "updated": updated, "version": self.version(),
                    "note": f"{name}: {len(added)} GCP(s) added, {len(updated)} updated"}
        return self.on_update_thread(run)

    def export_csv(self) -> tuple[str, bytes]:
        """(file name, CSV bytes) of the working set (the GCP tab's Export)."""
        text = self.on_update_thread(self.app.gcp_panel.export_markers)
        return f"{self.app.site.name}_gcps.csv", text.encode()
