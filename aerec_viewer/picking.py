"""The picking view: an image of the site laid out as a flat plane beside the cloud, where a
click becomes a pixel, and the loupe on it (the full-resolution pixels around a first click,
enlarged, where the second click places to a fraction of a pixel).

`PickingView` owns the /gcp/plane node and the loupe; what a click on the plane records is the
viewer's (ViewerApp.on_plane_click), the GCP markers drawn over it are gcp_marks'.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from recon_core.model.tiling import Window

from .display import FLAT_WXYZ, plane_hit, plane_point

if TYPE_CHECKING:
    import viser

    from .gcp_controller import GcpController
    from .gcp_marks import GcpMarks
    from .gcp_panel import GcpPanel
    from .imagery import ImageSource
    from .scene import SceneView
    from .views import ClientViews


@dataclass(frozen=True)
class PickPlane:
    """An image window drawn as a flat plane in the scene (display coordinates)."""

    window: Window
    position: np.ndarray
    wxyz: np.ndarray
    render_width: float
    render_height: float

    def hit(self, ray_origin, ray_direction) -> tuple[float, float] | None:
        return plane_hit(ray_origin, ray_direction, position=self.position, wxyz=self.wxyz,
                         render_width=self.render_width, render_height=self.render_height)

    def point_of(self, col: float, row: float, lift: float = 0.0) -> np.ndarray:
        """Display point of a full-image pixel on the plane (lifted above it by `lift`)."""
        fx, fy = self.window.fraction(col, row)
        return plane_point(fx, fy, position=self.position, wxyz=self.wxyz,
                           render_width=self.render_width, render_height=self.render_height,
                           lift=lift)


def pixel_from_ray(plane: PickPlane, ray_origin, ray_direction) -> tuple[float, float] | None:
    """Full-image pixel (col, row) where a click ray meets the picking plane, or None."""
    f = plane.hit(ray_origin, ray_direction)
    return None if f is None else plane.window.pixel(*f)


def layout_pick_plane(window: Window, bounds: tuple[np.ndarray, np.ndarray] | None,
                      gap: float = 0.1) -> PickPlane:
    """Place the picking plane flat, beside (east of) the displayed cloud, as tall as it (groups
    shown side by side make the cloud wider, not taller)."""
    if bounds is None:
        lo, hi = np.array([-500.0, -500.0, 0.0]), np.array([500.0, 500.0, 0.0])
    else:
        lo, hi = (np.asarray(b, dtype=np.float64) for b in bounds)
    size = float(max(hi[1] - lo[1], 1e-6))
    aspect = window.height / window.width
    w, h = (size, size * aspect) if aspect <= 1 else (size / aspect, size)
    pos = np.array([hi[0] + gap * size + w / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return PickPlane(window, pos, FLAT_WXYZ.copy(), float(w), float(h))


# The loupe: the first click on the image plane (when "Click zooms in first" is on) shows the
# LOUPE_PX x LOUPE_PX full-resolution pixels around it, each drawn as LOUPE_SCALE x LOUPE_SCALE
# texels (nearest neighbour, lossless), with a crosshair whose centre is left open; the second
# click there is the observation, to a fraction of a pixel.
LOUPE_PX = 40
LOUPE_SCALE = 16
LOUPE_CROSS = (255, 200, 0)


def loupe_window(width: int, height: int, image: str, col: float, row: float,
                 size: int = LOUPE_PX) -> Window:
    """The size x size window of an image (width x height) centred on pixel (col, row), shifted
    inside the image at its borders."""
    w, h = min(size, width), min(size, height)
    c0 = int(min(max(round(col) - size // 2, 0), width - w))
    r0 = int(min(max(round(row) - size // 2, 0), height - h))
    return Window(image, c0, r0, w, h)


def loupe_texture(gray: np.ndarray, win: Window, centre: tuple[float, float],
                  scale: int = LOUPE_SCALE) -> np.ndarray:
    """(h * scale, w * scale, 3) uint8: the window's pixels enlarged by pixel replication and a
    one-texel crosshair through the centre of the pixel `centre` (full-image col, row), open
    over that pixel and its neighbours so that it never covers what is being aimed at."""
    rgb = np.repeat(np.repeat(np.repeat(gray[..., None], 3, axis=2), scale, axis=0), scale, axis=1)
    fx, fy = win.fraction(*centre)
    H, W = rgb.shape[:2]
    cx, cy = int(np.clip(fx * W, 0, W - 1)), int(np.clip(fy * H, 0, H - 1))
    gap = int(1.5 * scale)
    cols = np.r_[0:max(cx - gap, 0), min(cx + gap + 1, W):W]
    rows = np.r_[0:max(cy - gap, 0), min(cy + gap + 1, H):H]
    rgb[cy, cols] = LOUPE_CROSS
    rgb[rows, cx] = LOUPE_CROSS
    return rgb


class PickingHost(Protocol):
    """What the picking view needs of the viewer."""

    server: viser.ViserServer
    images: ImageSource
    scene: SceneView                 # its tiles' windows
    gcp_panel: GcpPanel              # the GCP tab: chosen image, region, contrast, plane shown
    marks: GcpMarks                  # redrawn over the plane
    gcp: GcpController               # what a click records
    views: ClientViews               # the drag guard, framing a tab
    frame: str

    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray] | None: ...
    def submit(self, fn: Callable[[], object]) -> object: ...
    def note(self, text: str, level: str = "info") -> None: ...


class PickingView:
    """The picking plane and its loupe (scene node /gcp/plane). Changed only on the viewer's
    update thread, like every scene node."""

    def __init__(self, app: PickingHost):
        self.app = app
        self.plane: PickPlane | None = None
        self.loupe: tuple[Window, tuple[float, float]] | None = None   # (window, pixel zoomed on)
        # whose loupe it is: the GCP it was opened for (None: a new one) and the tab that opened
        # it. A click in it places that GCP only, and only from that tab: another tab sees the
        # loupe's pixels stretched over the plane it took for the whole image, and another GCP's
        # click at the loupe's spot would be recorded where the first one is
        self.loupe_gcp: str | None = None
        self.loupe_client: int | None = None
        self.reframe = False             # frame the clients once the plane is first drawn
        self._handle = None
        self._key = None                 # the layout's frame and cloud bounds
        self._token = None               # the newest texture read asked for
        self._views: dict[int, tuple] = {}   # client id -> its camera before the loupe
        self._regions: dict[str, Window] = {}

    def plane_nodes(self) -> list:
        """The picking image's node (none before it is drawn)."""
        return [] if self._handle is None else [self._handle]

    def look_at_plane(self, client) -> None:
        """Put a client's camera straight above the picking plane (for precise clicks)."""
        p = self.plane
        if p is None:
            return
        size = max(p.render_width, p.render_height)
        client.camera.far = 50.0 * size
        client.camera.up_direction = (0.0, 1.0, 0.0)
        client.camera.position = tuple(p.position + np.array([0.0, -1e-3 * size, 1.25 * size]))
        client.camera.look_at = tuple(p.position)

    def set_regions(self) -> None:
        """The GCP tab's regions of its chosen image: the whole image and each of its tiles."""
        img = self.app.gcp_panel.image.value
        self._regions = {"whole image": self.app.images.whole(img)}
        for tid, win in sorted(self.app.scene.tile_windows.items()):
            if win.image == img:
                self._regions[f"tile {tid.split(':')[-1]} ({win.width} x {win.height} at "
                              f"{win.col0}, {win.row0})"] = win
        self.app.gcp_panel.set_regions(list(self._regions)[1:])

    def current_window(self) -> Window:
        """The window the plane shows: the open loupe's in the chosen image, else the region's."""
        self.set_regions()
        if self.loupe is not None and self.loupe[0].image == self.app.gcp_panel.image.value:
            return self.loupe[0]
        panel = self.app.gcp_panel
        return self._regions.get(panel.region.value, self.app.images.whole(panel.image.value))

    def in_loupe(self, win: Window) -> bool:
        """Is this window (the plane's, or the one about to be drawn) the open loupe?"""
        return self.loupe is not None and self.loupe[0] == win

    def open_loupe(self, pix: tuple[float, float], client=None, image: str | None = None,
                   gcp: str | None = None) -> Window:
        """Show the full-resolution pixels around pix (in the plane's image, or `image`, the one
        chosen in the GCP tab) on the picking plane and put the client's camera straight above
        it; the next click, from that client, places `gcp` (None: a new GCP)."""
        if not image:
            assert self.plane is not None    # a loupe opens on the plane shown, or on `image`
            image = self.plane.window.image
        im = self.app.images.info(image)
        win = loupe_window(im.width, im.height, image, *pix)
        self.loupe = (win, (float(pix[0]), float(pix[1])))
        self.loupe_gcp = gcp
        self.loupe_client = None if client is None else client.client_id
        self.show(wait=True)
        if client is not None:
            cam = client.camera
            self._views[client.client_id] = (tuple(cam.position), tuple(cam.look_at),
                                             tuple(cam.up_direction))
            self.look_at_plane(client)
        self.app.gcp_panel.leave_loupe.disabled = False
        self.app.note(f"loupe on {image} around col {pix[0]:.0f}, row {pix[1]:.0f}: click the exact "
                      "pixel (or Leave the loupe)")
        return win

    def owns_loupe(self, gcp: str | None, client=None) -> bool:
        """Is the open loupe this GCP's, opened by this client (any, when either is unknown)?"""
        if self.loupe is None or self.loupe_gcp != gcp:
            return False
        return client is None or self.loupe_client is None or client.client_id == self.loupe_client

    def retarget(self, gcp: str | None) -> None:
        """The selection changed to `gcp`: a loupe opened for another GCP is closed (it shows
        that GCP's spot: a click there would record the new one where the old one is)."""
        if self.loupe is not None and self.loupe_gcp != gcp:
            self.close_loupe()

    def close_loupe(self, client=None) -> None:
        """Back to the region the loupe was opened from (and the client's view before it)."""
        if self.loupe is None:
            return
        self.loupe = None
        self.loupe_gcp = self.loupe_client = None
        self.app.gcp_panel.leave_loupe.disabled = True
        self.show(wait=True)
        for cid, c in list(self.app.server.get_clients().items()):
            view = self._views.get(cid)
            if view is not None and (client is None or cid == client.client_id):
                c.camera.up_direction = view[2]
                c.camera.position = view[0]
                c.camera.look_at = view[1]
        self._views.clear()

    def show(self, wait: bool = False) -> None:
        """(Re)draw the picking plane for the image and region chosen in the GCP tab.

        The texture (at most 2048 px a side) is read on a helper thread, so a first read of a
        large image never stalls the scene updates; `wait` reads it here (tests)."""
        if not self.app.gcp_panel.show_plane.value:
            if self._handle is not None:
                self._handle.remove()
            self._handle, self.plane, self._key = None, None, None
            self.app.marks.invalidate()
            return
        win = self.current_window()
        contrast = self.app.gcp_panel.contrast.value
        token = self._token = object()
        loupe = self.loupe if self.in_loupe(win) else None

        def texture() -> np.ndarray:
            tex = self.app.images.read(win, 2048, contrast)
            return tex if loupe is None else loupe_texture(tex, win, loupe[1])

        if wait:
            self._place(win, texture(), token)
            return

        def read() -> None:
            try:
                tex = texture()
            except Exception as exc:
                msg = f"cannot read {win.image}: {exc}"   # exc is unbound once the block ends
                self.app.submit(lambda: self.app.note(msg, "error"))
                return
            self.app.submit(lambda: self._place(win, tex, token))

        threading.Thread(target=read, name="aerec-plane-read", daemon=True).start()

    def _place(self, win: Window, tex: np.ndarray, token: object) -> None:
        if token is not self._token:            # a newer choice superseded this one
            return
        plane = layout_pick_plane(win, self.app.scene_bounds())
        rgb = tex if tex.ndim == 3 else np.repeat(tex[..., None], 3, axis=2)
        h = self.app.server.scene.add_image("/gcp/plane", rgb, plane.render_width, plane.render_height,
                                            # the loupe's enlarged pixels must stay sharp
                                            format="png" if self.in_loupe(win) else "jpeg", jpeg_quality=90,
                                            wxyz=plane.wxyz, position=plane.position,
                                            cast_shadow=False, receive_shadow=False)

        def clicked(ev) -> None:
            if self.app.views.moved_just_before(ev.client_id, time.time()):
                self.app.submit(lambda: self.app.note("the view moved during that click (a drag): nothing "
                                                      "recorded; click without moving the mouse", "warning"))
                return
            self.app.submit(lambda: self.app.gcp.on_plane_click(ev.ray_origin, ev.ray_direction, ev.client))

        h.on_click(clicked)
        self._handle, self.plane = h, plane
        self._key = self._bounds_key()
        self.app.marks.invalidate()
        self.app.marks.draw()
        if self.reframe:                    # the first view should show the plane too
            self.reframe = False
            for client in self.app.server.get_clients().values():
                self.app.views.frame_client(client)

    def _bounds_key(self):
        b = self.app.scene_bounds()
        return None if b is None else (self.app.frame, tuple(np.round(np.r_[b[0], b[1]], 3)))

    def reset_layout(self) -> None:
        """The displayed frame changed: lay the plane out again at the next update."""
        self._key = ("reset",)

    def relayout(self) -> None:
        """Keep the plane beside the cloud as the cloud grows (moved, or redrawn when its size
        or the frame changed)."""
        if self.plane is None or self._handle is None:
            return
        key = self._bounds_key()
        if key is None or key == self._key:
            return
        old = self.plane
        new = layout_pick_plane(old.window, self.app.scene_bounds())
        grow = new.render_width / old.render_width
        if key[0] != (self._key or (None,))[0] or not (0.8 < grow < 1.25):
            self.show(wait=True)            # the texture is cached by now
            return
        moved = np.linalg.norm(new.position - old.position) / old.render_width
        if moved > 0.05:
            self._handle.position = tuple(new.position)
            self.plane = PickPlane(old.window, new.position, old.wxyz, old.render_width, old.render_height)
            self.app.marks.invalidate()
        self._key = key
