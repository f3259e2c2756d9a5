"""The GCP markers: every `/gcp` node but the picking plane itself.

Rings (one node per place and width) and labels on the picking plane and on each group's cloud,
the residual vectors on the plane with their legend, and the drag handle on the selected GCP's
observation in the loupe. `GcpMarks.draw` keeps them equal to the GCP working set, the view and
the plane; the viewer calls it after every change and reads the rest of its state through `app`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, NamedTuple, Protocol

import numpy as np

from .display import quat_to_matrix
from .gcp_session import add_observation
from .picking import PickPlane, pixel_from_ray
from .scene import safe_name

if TYPE_CHECKING:
    import viser

    from recon_core.euclidean.ground_reference import GroundReference

    from .gcp_controller import GcpController
    from .gcp_panel import GcpPanel
    from .gcp_session import GcpSession
    from .picking import PickingView
    from .worker import ReconWorker

MARK_RING_PX = 11.0     # radius of a GCP marker ring on screen (pixels), whatever the zoom
MARK_SEL = (255, 220, 0)
MARK = (230, 40, 40)
MARK_CHECK = (40, 200, 255)
MARK_OFF = (150, 150, 150)   # a disabled GCP


def ring_segments(r: float, n: int = 12) -> np.ndarray:
    """(n, 2, 3) segments of a circle of radius r in the local xy plane."""
    a = np.linspace(0.0, 2.0 * np.pi, n + 1)
    p = np.stack([r * np.cos(a), r * np.sin(a), np.zeros_like(a)], axis=1).astype(np.float32)
    return np.stack([p[:-1], p[1:]], axis=1)


def label_offset(r: float, on_plane: bool) -> np.ndarray:
    """Where a marker's label sits: beside its ring, not on the point."""
    return np.array([r, r, 0.0]) if on_plane else np.array([r, 0.0, r])


class _Marker(NamedTuple):
    """A GCP's marker in one place (the picking plane, a group's cloud): its ring is drawn with
    the others of that place (`GcpMarks._draw_rings`), its label is its own node."""

    label: viser.LabelHandle
    colour: tuple[int, int, int]
    radius: float
    pos: np.ndarray
    text: str = ""


class GcpMarksHost(Protocol):
    """What the markers need of the viewer: the working set and its controller, the picking
    plane, the GCP tab's selection, the reference orthoimage, the frames and the scene."""

    server: viser.ViserServer        # its scene: the marker nodes
    worker: ReconWorker              # the newest display snapshot (transforms per group)
    session: GcpSession              # the working set
    gcp: GcpController               # affine positions, edits
    gcp_panel: GcpPanel              # the GCP tab: the selected GCP
    picking: PickingView             # the plane and its loupe
    reference: GroundReference | None  # the reference orthoimage (ground positions on it), or None
    models: dict
    frame: str

    def transforms(self, snap) -> dict: ...
    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray] | None: ...
    def submit(self, fn: Callable[[], object]) -> object: ...
    def note(self, text: str, level: str = "info") -> None: ...


class GcpMarks:
    """The markers' scene nodes and the state that decides when they are redrawn."""

    def __init__(self, app: GcpMarksHost):
        self.app = app
        self.items: dict[str, _Marker] = {}   # one per GCP and place: path -> its label, ...
        self.rings: dict[str, viser.LineSegmentsHandle] = {}    # <place>/rings[_selected] -> merged ring node
        self.residual_nodes: list = []        # the residual vectors on the plane and their legend
        self.drag_handle = None               # the drag handle on the selected observation (loupe)
        self.drag_key = None
        self.key = None                       # what the markers were last drawn for (None: redraw)
        self.ring_view: tuple | None = None   # (distance to look-at, fov, height px) of the view
        #                                       that moved last: the rings' size

    def invalidate(self) -> None:
        """Redraw at the next `draw` (the state they depend on changed)."""
        self.key = None

    def marker_positions(self) -> dict[str, tuple[np.ndarray, tuple[int, int, int], str]]:
        """Scene path -> (display position, colour, label) of every GCP marker to show: on the
        picking plane for observations in its window, on each group's cloud for placed GCPs."""
        app = self.app
        snap_T = {g: T for g, T in app.transforms(app.worker.snapshot()).items() if T is not None}
        sel = app.gcp_panel.selected()
        roles = {g.id: g.role if g.enabled else "disabled" for g in app.session.gcps}
        labels = {g.id: g.id if g.sigma_h_m is None else f"{g.id} (h +-{g.sigma_h_m:.0f} m)"
                  for g in app.session.gcps}

        def colour(gid):
            return MARK_SEL if gid == sel else {"check": MARK_CHECK, "disabled": MARK_OFF}.get(roles.get(gid, ""), MARK)

        want = {}
        r = self.radius()
        pl, gs = app.picking.plane, app.session.gcps
        if pl is not None:
            if app.reference is not None and pl.window.image == app.reference.ortho.name and gs:
                # on the reference orthoimage: each GCP's ground position
                cols, rows = app.reference.pixel_of([g.lon for g in gs], [g.lat for g in gs])
                pix = {g.id: (float(c), float(rr)) for g, c, rr in zip(gs, cols, rows)}
            else:
                pix = {g.id: g.observations[pl.window.image] for g in gs if pl.window.image in g.observations}
            for gid, (c, rr) in pix.items():
                if pl.window.contains([(c, rr)])[0]:
                    want[f"/gcp/plane_marks/{safe_name(gid)}"] = (pl.point_of(c, rr, lift=0.5 * r), colour(gid),
                                                                  labels.get(gid, gid))
        shown: set[str] = set()
        for g, T in sorted(snap_T.items()):
            for gid, xyz in app.gcp.affine_positions(g).items():
                if app.frame == "euclidean" and gid in shown:
                    continue                  # groups share the ENU frame: one marker per GCP
                shown.add(gid)
                want[f"/gcp/cloud/g{g}/{safe_name(gid)}"] = (
                    T.apply(np.asarray(xyz)[None])[0].astype(float), colour(gid), labels.get(gid, gid))
        return want

    def radius(self) -> float:
        """World radius of a marker ring MARK_RING_PX screen pixels wide in the view that moved
        last (rings keep their size on screen as the operator zooms); before any view, a
        fraction of the scene."""
        app = self.app
        if self.ring_view is not None:
            d, fov, h_px = self.ring_view
            return MARK_RING_PX * 2.0 * d * np.tan(fov / 2.0) / max(h_px, 1)
        b = app.scene_bounds()
        size = 1000.0 if b is None else float(max(b[1][0] - b[0][0], b[1][1] - b[0][1], 1e-6))
        return size / 90.0

    def draw(self) -> None:
        """Add, move, recolour or remove GCP markers (rings with labels: the point itself stays
        visible inside) to match the state."""
        app = self.app
        snap_T = app.transforms(app.worker.snapshot())
        key = (app.session.version, app.gcp_panel.select.value, app.frame,
               None if app.picking.plane is None else (app.picking.plane.window, tuple(app.picking.plane.position)),
               tuple((g, id(T)) for g, T in sorted(snap_T.items())), len(app.models))
        if key == self.key:
            return
        self.key = key
        want = self.marker_positions()
        r = self.radius()
        sc = app.server.scene
        for name in [n for n in self.items if n not in want]:
            self.items.pop(name).label.remove()
        for name, (pos, col, text) in want.items():
            have = self.items.get(name)
            on_plane = name.startswith("/gcp/plane_marks/") and app.picking.plane is not None
            if have is not None and have.colour == col and have.text == text and abs(have.radius / r - 1) < 0.1:
                if np.linalg.norm(have.pos - pos) > 1e-6 * r:
                    have.label.position = tuple(pos + label_offset(have.radius, on_plane))
                    self.items[name] = have._replace(pos=pos)
                continue
            if have is not None:
                have.label.remove()
            label = sc.add_label(f"{name}_label", text, position=tuple(pos + label_offset(r, on_plane)),
                                 anchor="bottom-left", font_screen_scale=0.7)
            self.items[name] = _Marker(label, col, r, pos, text)
        self._draw_rings()
        self._draw_residual_vectors()
        self._draw_drag_handle()

    def label_nodes(self) -> list:
        """The GCPs' labels and rings, the residual vectors and their legend (what the moving
        display sheds as "labels": the rings are fat-line instances, a frame's millisecond each
        few dozen in software WebGL)."""
        return [m.label for m in self.items.values()] + list(self.rings.values()) + list(self.residual_nodes)

    def _draw_rings(self) -> None:
        """The markers' rings, merged into one node per place (the picking plane, each group's
        cloud) and width (the selected GCP's is wider): a node is a draw call, and software
        WebGL pays about a millisecond for each, a frame for 40 markers."""
        app = self.app
        flat = np.eye(3, dtype=np.float32)                 # rings on the clouds lie in xy
        on_plane = flat if app.picking.plane is None else \
            quat_to_matrix(np.asarray(app.picking.plane.wxyz)).astype(np.float32)
        sets: dict[str, list] = {}
        for name, (_, col, r, pos, _) in self.items.items():
            place = name.rsplit("/", 1)[0]
            R = on_plane if place == "/gcp/plane_marks" else flat
            seg = ring_segments(r) @ R.T + np.asarray(pos, np.float32)
            sets.setdefault(f"{place}/rings{'_selected' if col == MARK_SEL else ''}", []).append(
                (seg, np.broadcast_to(np.array(col, np.uint8), seg.shape)))
        sc = app.server.scene
        for path in [p for p in self.rings if p not in sets]:
            self.rings.pop(path).remove()
        for path, parts in sets.items():
            self.rings[path] = sc.add_line_segments(
                path, np.concatenate([p[0] for p in parts]).astype(np.float32),
                np.ascontiguousarray(np.concatenate([p[1] for p in parts])),
                thickness=3.0 if path.endswith("_selected") else 2.0, thickness_units="screen")

    def drag_target(self) -> tuple[str, str, tuple[float, float]] | None:
        """(GCP, image, pixel) the drag handle adjusts: the selected GCP's observation, when the
        loupe shows it (full-resolution pixels: a drag there is as precise as a click)."""
        app = self.app
        gid, pl = app.gcp_panel.selected(), app.picking.plane
        if gid is None or pl is None or app.picking.loupe is None or not app.picking.in_loupe(pl.window) \
                or gid not in app.session.ids or app.picking.loupe_gcp != gid:
            return None
        ob = app.session.get(gid).observations.get(pl.window.image)
        if ob is None or not pl.window.contains([ob])[0]:
            return None
        return gid, pl.window.image, (float(ob[0]), float(ob[1]))

    def _draw_drag_handle(self) -> None:
        """Arrows in the plane (no rotation, no height) on the selected GCP's observation in the
        loupe: dragging them moves the observation, which is recorded when the drag ends."""
        app = self.app
        want = self.drag_target()
        pl = app.picking.plane                # not None when want is not (drag_target)
        key = None if want is None or pl is None else (want, tuple(pl.position))
        if key == self.drag_key:
            return
        if self.drag_handle is not None:
            self.drag_handle.remove()
            self.drag_handle = None
        self.drag_key = key
        if want is None:
            return
        gid, image, ob = want
        assert pl is not None
        h = app.server.scene.add_transform_controls(
            "/gcp/drag", scale=0.18 * pl.render_width, line_width=2.0, disable_rotations=True,
            active_axes=(True, True, False), depth_test=False,
            position=tuple(pl.point_of(*ob, lift=0.004 * pl.render_width)))

        @h.on_update
        def _(ev) -> None:
            if ev.phase == "end":
                pos = np.array(ev.target.position, dtype=np.float64)
                app.submit(lambda: self.on_handle_dragged(gid, image, pos, ev.client, handle=h, plane=pl))
        self.drag_handle = h

    def on_handle_dragged(self, gid: str, image: str, position, client=None, handle=None,
                          plane: PickPlane | None = None) -> tuple[float, float] | None:
        """The drag handle was released at `position` (display coordinates, on `plane`, the plane
        it was drawn on): the GCP's observation in `image` moves to the pixel under it. A handle
        replaced meanwhile (the plane moved, another tab edited) is ignored."""
        app = self.app
        if handle is not None and handle is not self.drag_handle:
            return None
        pl = plane or app.picking.plane
        if pl is None or pl.window.image != image or gid not in app.session.ids:
            self.drag_key = None
            self._draw_drag_handle()
            return None
        p = np.asarray(position, dtype=np.float64)
        pix = pixel_from_ray(pl, p + np.array([0.0, 0.0, pl.render_width]), np.array([0.0, 0.0, -1.0]))
        if pix is None:
            self.drag_key = None
            self._draw_drag_handle()
            app.note("the drag left the image: nothing moved", "warning")
            return None
        was = app.session.get(gid).observations.get(image)
        if was is not None and np.hypot(pix[0] - was[0], pix[1] - was[1]) < 1e-3:
            return None                      # pressed and released without moving
        add_observation(app.session, gid, image, *pix)
        app.gcp.changed(select="keep", note=f"{gid}: moved in {image} to col {pix[0]:.2f}, "
                                              f"row {pix[1]:.2f} (dragged)")
        return pix

    def resize(self) -> None:
        """Redraw the rings at the size the last zoom asks for."""
        self.key = None
        self.draw()

    RESIDUAL_SCALE = 20.0          # residual vectors on the image plane: 1 px drawn as >= 20 px

    def residual_scale(self) -> float:
        """The vectors' magnification for the window on the plane: 1 px of residual is drawn as
        about 5 % of the window (a round 20, 50, 100, 200 or 500), so a 1 px residual shows on a
        whole 2000 px image as well as in the loupe."""
        app = self.app
        if app.picking.plane is None:
            return self.RESIDUAL_SCALE
        w = app.picking.plane.window
        target = 0.05 * max(w.width, w.height)
        return float(next((n for n in (20, 50, 100, 200, 500) if n >= target), 500))

    def residual_vectors(self) -> dict[str, tuple[tuple[float, float], tuple[float, float]]]:
        """GCP id -> (observed pixel, residual observed - reprojected) in the plane's image, for
        the GCPs observed there and in another registered image of its group."""
        from recon_core.euclidean.gcp_transfer import observation_residuals

        app = self.app
        if app.picking.plane is None:
            return {}
        img = app.picking.plane.window.image
        model = next((m for m in app.models.values() if img in m.images), None)
        if model is None:
            return {}
        out = {}
        for g in app.session.gcps:
            if img in g.observations:
                res = observation_residuals(model, g.observations)
                if img in res:
                    out[g.id] = (g.observations[img], res[img])
        return out

    def _draw_residual_vectors(self) -> None:
        """Orange segments from each observation along its residual (x residual_scale()), with a
        legend; red when the residual exceeds 1 px."""
        app = self.app
        for h in self.residual_nodes:
            h.remove()
        self.residual_nodes = []
        vecs = self.residual_vectors()
        if not vecs or app.picking.plane is None:
            return
        pl = app.picking.plane
        k = self.residual_scale()
        seg = np.array([[pl.point_of(c, r, lift=0.002 * pl.render_width),
                         pl.point_of(c + k * dx, r + k * dy, lift=0.002 * pl.render_width)]
                        for (c, r), (dx, dy) in vecs.values()], dtype=np.float32)
        big = np.array([np.hypot(dx, dy) > 1.0 for _, (dx, dy) in vecs.values()])
        cols = np.where(big[:, None, None], np.array([220, 30, 30]), np.array([255, 150, 0]))
        cols = np.broadcast_to(cols, seg.shape).astype(np.uint8)
        sc = app.server.scene
        self.residual_nodes.append(sc.add_line_segments("/gcp/plane_residuals", seg, cols,
                                                         thickness=3.0, thickness_units="screen"))
        w = pl.window
        self.residual_nodes.append(sc.add_label(
            "/gcp/plane_residuals_legend", f"residual vectors x{k:g} (red: > 1 px)",
            position=tuple(pl.point_of(w.col0, w.row0 + w.height, lift=0.002 * pl.render_width)),
            anchor="top-left", font_screen_scale=0.7))
