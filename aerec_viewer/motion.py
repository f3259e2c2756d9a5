"""The display while a view moves: lighter, so that an orbit stays fluid without a GPU.

At rest the page draws once and may take its time: every point of the budget, the tiles, the
labels, the picking image. While any tab's view moves (its camera messages), the clouds are drawn
from their moving subsamples (scene.SceneView.set_moving) and what the governor sheds is hidden
(framerate.SHED); once the views rest, everything comes back. Every few seconds of a gesture and
at its end the governor reads the frame rate the page drew (framerate.ViewRateMeter) and resizes
the moving display.

Everything here runs on the viewer's update thread, except `moved`, which the camera messages
call from the server's threads.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import TYPE_CHECKING

import numpy as np

from .framerate import SHED, MotionGovernor

if TYPE_CHECKING:
    from .app import ViewerApp

REST_MIN_S = 1.0          # the views rest once no camera message came for this long, or for
REST_MESSAGES = 3.0       # this many of the recent intervals between messages (a slow page
REST_MAX_S = 2.0          # sends them far apart), at most this long


class MotionDisplay:
    """Switches the scene between its rest and moving displays, and governs the moving one."""

    def __init__(self, app: "ViewerApp"):
        self.app = app
        self.governor = MotionGovernor()
        self.moving = False
        self._lock = threading.Lock()
        self._last = -np.inf                 # monotonic time of the newest camera message
        self._gaps: deque[float] = deque(maxlen=8)
        self._asked = False                  # a switch to moving is queued
        self._hidden: list = []              # (kind, handle) hidden for the motion
        self.note = ""                       # what the governor did, for the Display panel

    # -- from the camera messages (server threads) ------------------------------------------------
    def moved(self, t: float) -> None:
        """A view moved at monotonic time t: switch to the moving display (once, queued)."""
        with self._lock:
            if t - self._last < REST_MAX_S:
                self._gaps.append(t - self._last)
            self._last = t
            ask = not self.moving and not self._asked
            self._asked = self._asked or ask
        if ask:
            self.app.submit(self._start)

    def rest_s(self) -> float:
        """How long without a camera message means the views rest."""
        with self._lock:
            gap = float(np.median(self._gaps)) if self._gaps else 0.0
        return float(min(REST_MAX_S, max(REST_MIN_S, REST_MESSAGES * gap)))

    # -- on the update thread -------------------------------------------------------------------
    def _start(self) -> None:
        with self._lock:
            self._asked = False
        if not self.moving:
            self.moving = True
            self._apply()

    def tick(self, now: float | None = None) -> None:
        """Each update: back to rest once the views rest; the governor on a new measure. The
        moving subsamples are rebuilt when a gesture starts, if the cloud or the budget changed
        since (scene.sync_moving): a growing cloud costs no traffic at rest."""
        now = time.monotonic() if now is None else now
        if self.moving and now - self._last > self.rest_s():
            self.moving = False
            self._apply()
        self._govern(now)

    def _apply(self) -> None:
        """Show the display that matches `moving`."""
        self.app.scene.set_moving(self.moving, self.governor.budget)
        self._shed()

    def _shed(self) -> None:
        """While moving, hide the kinds the governor sheds; at rest show again what was hidden
        for the motion and is still the owners' (a node replaced meanwhile is theirs to show)."""
        want = set(self.governor.hidden()) if self.moving else set()
        keep = []
        for kind, h in self._hidden:
            if kind in want:
                keep.append((kind, h))
            elif any(h is x for x in self.nodes(kind)):
                h.visible = True
        self._hidden = keep
        for kind in want:
            for h in self.nodes(kind):
                if h.visible and not any(h is x for _, x in self._hidden):
                    h.visible = False
                    self._hidden.append((kind, h))

    def nodes(self, kind: str) -> list:
        """The scene nodes of one of framerate.SHED, as their owners hold them now."""
        app = self.app
        if kind == "tiles":
            return app.scene.tile_nodes()
        if kind == "labels":
            return app.marks.label_nodes() + app.scene.label_nodes()
        if kind == "image":
            return app.picking.plane_nodes()
        raise ValueError(f"not a kind of node shed while moving: {kind}")

    def _govern(self, now: float) -> None:
        fps = self.app.view_rate.rate(now)
        if fps is None:
            return
        scene, gov = self.app.scene, self.governor
        drawn = scene.moving_points()
        if not gov.observe(fps, drawn):
            return
        if gov.budget is not None and gov.budget >= scene.displayed_points():
            gov.budget = None                 # as fast with every point: nothing to thin
        scene.moving_budget = gov.budget
        if self.moving:
            self._apply()
        source = "drew" if self.app.view_rate.source == "drawn" else "moved at"
        what = f"{gov.budget:,} points" if gov.budget is not None else "every point"
        gone = [SHED_WORDS[k] for k in gov.hidden()]
        if gone:
            what += ", without " + (" and ".join(gone) if len(gone) < 3 else f"{gone[0]}, {gone[1]} and {gone[2]}")
        self.note = (f"While a view moves: {what} (the page {source} {fps:.0f} frames/s with {drawn:,} "
                     f"points; target {gov.TARGET_FPS:g}). At rest: the point budget.")
        self.app.recon.said_motion(self.note, lowered=gov.budget is not None or bool(gone))


SHED_WORDS = {"tiles": "the tiles", "labels": "the GCP marks and labels", "image": "the picking image"}
