"""Each browser tab's view of the scene: framing the cloud when the tab connects (and on
"Reset view"), zoom toward the spot under the cursor (shift+click), and when its camera last
moved (a click that arrives during a drag records nothing)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from .display import plane_point
from .framerate import counter_iframe

if TYPE_CHECKING:
    import viser
    from viser._messages import KeyModifier

    from .app import ViewerApp

# A click that arrives within this many seconds of its client's camera moving was a drag (an
# orbit that ended where it started, a wobble while pressing): it records nothing
DRAG_GUARD_S = 0.35


class ClientViews:
    """The tabs' cameras (viser clients) of one viewer."""

    ZOOM_STEP = 2.0        # shift+click: this much closer to the spot; ctrl+shift+click: back

    def __init__(self, app: "ViewerApp"):
        self.app = app
        self.moved: dict[int | None, tuple] = {}   # client id -> (position, wxyz, time it moved)
        self.app.server.on_client_connect(self.on_connect)
        self.app.server.on_client_disconnect(lambda c: self.app.view_rate.forget(c.client_id))
        zooms: tuple[tuple[KeyModifier, float], ...] = (("shift", self.ZOOM_STEP),
                                                        ("cmd/ctrl+shift", 1.0 / self.ZOOM_STEP))
        for modifier, factor in zooms:
            def zoom(ev: viser.SceneClickEvent, f: float = factor) -> None:
                self.app.submit(lambda: self.zoom_at(ev.client, ev.ray_origin, ev.ray_direction, f))

            self.app.server.scene.on_click(modifier=modifier)(zoom)

    def on_connect(self, client) -> None:
        self.app.gcp_panel.note_choice(client, chooser=False)   # what this tab sees at first
        client.camera.on_update(self.camera_update)
        ws = getattr(self.app, "workspace", None)
        if ws is not None:      # the page counts the frames it draws (framerate.py)
            client.gui.add_html(counter_iframe(ws.url, client.client_id), order=-1e9)
        self.app.submit(lambda: self.frame_client(client))

    def camera_update(self, camera) -> None:
        """Remember when each client's view last moved (the drag guard of on_plane_click, the
        frame rate meter, the display while a view moves)."""
        key = camera.client.client_id
        pose = (np.asarray(camera.position, float).copy(), np.asarray(camera.wxyz, float).copy())
        old = self.moved.get(key)
        if old is None or not (np.allclose(old[0], pose[0], rtol=0, atol=1e-9)
                               and np.allclose(old[1], pose[1], rtol=0, atol=1e-9)):
            self.moved[key] = (*pose, time.time())
            now = time.monotonic()
            self.app.view_rate.moved(key, now)
            self.app.motion.moved(now)          # the lighter display while it moves
            d = float(np.linalg.norm(np.asarray(camera.position) - np.asarray(camera.look_at)))
            view = (d, float(camera.fov), int(camera.image_height))
            before = self.app.marks.ring_view
            self.app.marks.ring_view = view
            if before is None or abs(d / max(before[0], 1e-12) - 1.0) > 0.2:
                self.app.submit(self.app.marks.resize)

    def moved_just_before(self, client_id: int | None, t_click: float) -> bool:
        """Did this client's view move during the DRAG_GUARD_S before a click (a drag)?"""
        moved = self.moved.get(client_id)
        return moved is not None and 0.0 <= t_click - moved[2] < DRAG_GUARD_S

    def frame_client(self, client) -> None:
        """Point a client's camera at the cloud, obliquely from the south, leaving room for the
        panel on the right (the picking plane lies further east: "Look at the image plane")."""
        b = self.app.scene_bounds()
        if b is None:
            return
        lo, hi = (np.asarray(v, dtype=np.float64) for v in b)
        c = (lo + hi) / 2
        size = float(max(hi[0] - lo[0], hi[1] - lo[1], 1e-6))
        look = c + np.array([0.22 * size, 0.0, 0.0])      # the panel covers the right side
        client.camera.far = 50.0 * size
        client.camera.near = 1e-4 * size
        client.camera.max_orbit_distance = 20.0 * size
        client.camera.up_direction = (0.0, 0.0, 1.0)
        client.camera.position = tuple(look + size * np.array([0.0, -0.6, 0.7]))
        client.camera.look_at = tuple(look)

    def zoom_at(self, client, ray_origin, ray_direction, factor: float) -> np.ndarray:
        """Zoom toward the spot under the cursor (viser's wheel zooms toward the view's centre):
        the camera moves along the click ray, 1 - 1/factor of the way to what the ray meets (the
        picking plane, else the nearest displayed point, else the depth of the view's centre),
        and keeps its orientation, so the spot stays under the cursor. Returns the spot."""
        o = np.asarray(ray_origin, float)
        d = np.asarray(ray_direction, float)
        d = d / np.linalg.norm(d)
        spot = None
        pl = self.app.picking.plane
        hit = None if pl is None else pl.hit(o, d)
        if pl is not None and hit is not None:
            fx, fy = hit
            spot = plane_point(fx, fy, position=pl.position, wxyz=pl.wxyz,
                               render_width=pl.render_width, render_height=pl.render_height)
        if spot is None:
            spot = self.app.scene.nearest_display_point(o, d)
        look = np.asarray(client.camera.look_at, float)
        if spot is None or (spot - o) @ d <= 0:
            spot = o + max(float((look - o) @ d), 1e-6) * d
        shift = (1.0 - 1.0 / factor) * (spot - o)
        with client.atomic():
            client.camera.position = tuple(o + shift)
            client.camera.look_at = tuple(look + shift)
        return spot
