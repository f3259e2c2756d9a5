"""Stable scene handles for clouds, tiles, GCP markers and the picking image plane.

`SceneView.sync` applies a worker snapshot to the scene. It is called from the viewer's update
thread only, inside `server.atomic()`. Scene paths are stable, so updates replace nodes:

  /recon/g<g>/<kind>/chunk_<k>     point-cloud chunks (kind: sparse, dense); float32, local origin
  /recon/g<g>/<kind>/moving        what is drawn instead while a view moves (set_moving)
  /recon/g<g>/tiles/outlines       registered tile footprints, one node per group (each node is
                                   a draw call, and software WebGL pays ~1 ms for each)
  /recon/g<g>/tiles/<tile>/image   a tile's textured quad
  /recon/g<g>/tiles/newest         the newest tile, highlighted
  /gcp/plane                       the picking image plane; GCP markers: /gcp/plane_marks/rings
                                   and /gcp/cloud/g<g>/rings (one node each), a label per GCP

Points are sent as new chunks as they arrive (reassigning a node's points resends all of them:
growing one node to 1 M points in 10 steps sent 79 MB, one node a step 14 MB); a new generation
(ModelUpdated), a new frame transform, a budget change or too many chunks rebuilds the group's
chunks. Display decimation follows the point budget.

While a view moves, each cloud may be drawn from a nested subsample of its chunks instead, its
points sized for their number (`set_moving`; the budget comes from motion.py).
"""

from __future__ import annotations

import re
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from recon_core.model.tiling import Window

from .display import (
    ColorRanges,
    DisplayTransform,
    QuadFrame,
    auto_point_size,
    closest_point_to_ray,
    cloud_salt,
    color_ranges,
    display_fraction,
    keep_mask,
    point_colors,
    quad_frame,
    quad_image,
)
from .imagery import ImageSource
from .worker import CloudView, DisplaySnapshot, PointBatch, TileView, concat_batches

if TYPE_CHECKING:
    import viser

CHUNK_MAX = 250_000           # points per chunk node at a rebuild
MAX_CHUNKS = 48               # more incremental chunks than this: consolidate
PALETTE = np.array([(80, 160, 255), (255, 140, 60), (120, 210, 120), (220, 110, 220),
                    (240, 220, 80), (90, 220, 220)], dtype=np.uint8)
NEWEST = (255, 230, 0)
# How registered tiles are drawn. Textured tiles are what software WebGL spends most on: on a
# 3-date site (44 tiles stacked 3 deep) 7 frames/s while orbiting with or without points, 48
# with outlines (bench/bench_viewer.py --fps); under a dense cloud they are hardly seen.
TILE_MODES = {"auto": "textured while a group has no dense points shown, then outlines",
              "textured": "each tile's image, where the SfM put it",
              "outlines": "each tile's outline", "hidden": "no tiles"}


def safe_name(text: str) -> str:
    """A scene-path component from any id (tile ids hold ':' and '.')."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)


@dataclass
class Settings:
    """Display settings the panel controls."""

    point_size: float = 1.0              # multiple of the automatic size (display.auto_point_size)
    color_mode: str = "height"
    budget: int = 150_000                # points displayed at most (all groups and kinds); the
                                         # viewer lowers it on a slow page (framerate.py)
    tiles: str = "auto"                  # auto, textured, outlines, hidden (TILE_MODES)
    show_sparse: bool = True
    show_dense: bool = True


@dataclass
class _Chunk:
    handle: viser.PointCloudHandle
    xyz: np.ndarray                      # display coordinates sent
    batch: PointBatch                    # displayed subset (for recolouring)
    t_sent: float
    t_added: tuple[float, ...]           # t_added of the worker batches it holds


@dataclass
class _Cloud:
    generation: int = -1
    transform: DisplayTransform | None = None
    fraction: float = 1.0
    n_batches: int = 0
    chunks: list[_Chunk] = field(default_factory=list)
    ranges: ColorRanges = field(default_factory=ColorRanges)
    extent: float = 1.0
    box: tuple | None = None             # its footprint: 2-98 % xy bounds (lo, hi), grown per chunk
    next_k: int = 0
    kept: float = 1.0                    # the store's own thinning when this generation began
    moving: "_Moving | None" = None      # the subsample drawn while a view moves


@dataclass
class _Moving:
    handle: viser.PointCloudHandle
    n: int
    key: tuple                           # what it was built from (_moving_key)


@dataclass
class _TileNode:
    version: int
    transform: DisplayTransform
    corners: np.ndarray
    color: tuple[int, ...]               # (r, g, b)
    image: viser.ImageHandle | None = None
    frame: QuadFrame | None = None       # QuadFrame the texture was warped for


def _footprint(xyz: np.ndarray) -> tuple[float, tuple[np.ndarray, np.ndarray]]:
    """(largest 2-98 % span, the 2-98 % xy bounds) of points in the display frame."""
    lo, hi = np.percentile(xyz[:, :2], 2, axis=0), np.percentile(xyz[:, :2], 98, axis=0)
    return float(max(np.max(hi - lo), 1e-6)), (lo, hi)


def union_area(boxes: list[tuple[np.ndarray, np.ndarray]], cells: int = 128) -> float:
    """Area covered by axis-aligned boxes (lo, hi): the date groups overlap in the Euclidean
    frame and lie side by side in the affine one (counted on a cells x cells raster)."""
    boxes = [(np.asarray(lo, float), np.asarray(hi, float)) for lo, hi in boxes
             if np.all(np.isfinite(lo)) and np.all(np.isfinite(hi)) and np.all(hi > lo)]
    if not boxes:
        return 0.0
    lo = np.min([b[0] for b in boxes], axis=0)
    hi = np.max([b[1] for b in boxes], axis=0)
    step = (hi - lo) / cells
    centres = [lo[k] + step[k] * (np.arange(cells) + 0.5) for k in range(2)]
    covered = np.zeros((cells, cells), bool)
    for blo, bhi in boxes:
        covered |= np.outer((centres[1] >= blo[1]) & (centres[1] <= bhi[1]),
                            (centres[0] >= blo[0]) & (centres[0] <= bhi[0]))
    return float(covered.mean() * np.prod(hi - lo))


class SceneView:
    """Owns the reconstruction's scene nodes and keeps them equal to the newest snapshot."""

    def __init__(self, server, images: ImageSource, tile_windows: dict[str, Window] | None = None):
        self.server = server
        self.tile_windows = dict(tile_windows or {})
        self.scene = server.scene
        self.images = images
        self.settings = Settings()
        self._clouds: dict[tuple[int, str], _Cloud] = {}
        self._tiles: dict[tuple[int, str], _TileNode] = {}
        self._newest: dict[int, tuple[str, int, int]] = {}
        self._newest_nodes: dict[int, tuple[viser.LineSegmentsHandle, viser.LabelHandle]] = {}
        self._tile_mode: dict[int, str] = {}
        self._outlines: dict[int, viser.LineSegmentsHandle] = {}   # group -> its outlines node
        self.finished = False
        self._slack = 1.5
        self.sent_log: list[dict] = []    # one entry per point chunk sent (for the bench)
        self.image_index = {name: k for k, name in enumerate(sorted(images.images))}
        self.moving = False               # a view moves: the clouds' moving subsamples are drawn
        self.moving_budget: int | None = None    # points drawn while moving (None: those shown)

    # -- points -------------------------------------------------------------------------------
    def sync(self, snap: DisplaySnapshot, transforms: dict[int, DisplayTransform | None]) -> int:
        """Apply a snapshot; returns the number of points sent. While the cloud grows, its
        display is thinned again only when the budget is overshot by half (each rebuild resends
        it); once the run is over, the display holds the budget."""
        total = sum(g.sparse.n + (g.dense.n if self.settings.show_dense else 0)
                    for g in snap.groups.values())
        frac = display_fraction(total, self.settings.budget)
        self._slack = 1.02 if snap.status in ("done", "reopened", "failed", "stopped") else 1.5
        sent = 0
        for g, gs in snap.groups.items():
            T = transforms.get(g)
            if T is None:
                continue
            for kind, cloud in (("sparse", gs.sparse), ("dense", gs.dense)):
                sent += self._sync_cloud(g, kind, cloud, T, frac)
            self._sync_tiles(g, gs.tiles, gs.newest_tile, T, dense=gs.dense.n > 0)
        if sent:
            size = self.point_size()
            if any(c.handle.point_size != size for st in self._clouds.values() for c in st.chunks):
                self.apply_point_size(size)
        return sent

    def _sync_cloud(self, g: int, kind: str, cloud: CloudView, T: DisplayTransform,
                    frac: float) -> int:
        key = (g, kind)
        st = self._clouds.setdefault(key, _Cloud())
        visible = self._chunks_visible(kind, st)
        rebuild = (st.generation != cloud.generation or st.transform is not T
                   or frac < st.fraction / self._slack or (frac > st.fraction * 1.5 and st.fraction < 1.0)
                   or len(st.chunks) > MAX_CHUNKS or len(cloud.batches) < st.n_batches)
        if rebuild:
            return self._rebuild(key, st, cloud, T, frac, visible)
        if len(cloud.batches) == st.n_batches:
            return 0
        new = cloud.batches[st.n_batches:]
        st.n_batches = len(cloud.batches)
        return self._add_chunk(key, st, new, T, visible)

    def _rebuild(self, key, st: _Cloud, cloud: CloudView, T: DisplayTransform, frac: float,
                 visible: bool) -> int:
        for c in st.chunks:
            c.handle.remove()
        st.chunks = []
        st.generation, st.transform, st.fraction = cloud.generation, T, frac
        st.kept = cloud.kept_fraction
        st.n_batches = len(cloud.batches)
        st.next_k = 0
        allb = concat_batches(cloud.batches)
        if len(allb) == 0:
            return 0
        sub = allb.subset(keep_mask(allb.ids, frac * cloud.kept_fraction, cloud_salt(*key)))
        xyz = T.apply(sub.xyz)
        if len(xyz):
            st.ranges = color_ranges(xyz[:, 2], sub.n_views, sub.reproj)
            st.extent, st.box = _footprint(xyz)
        sent = 0
        for s in range(0, len(sub), CHUNK_MAX):
            part = sub.subset(slice(s, s + CHUNK_MAX))
            sent += self._send(key, st, part, xyz[s:s + CHUNK_MAX], visible,
                               tuple(b.t_added for b in cloud.batches))
        return sent

    def _add_chunk(self, key, st: _Cloud, batches: tuple[PointBatch, ...], T: DisplayTransform,
                   visible: bool) -> int:
        b = concat_batches(batches)
        sub = b.subset(keep_mask(b.ids, st.fraction * st.kept, cloud_salt(*key)))
        if len(sub) == 0:
            return 0
        xyz = T.apply(sub.xyz)
        if not st.chunks:                  # first points of this generation: fix the ranges
            st.ranges = color_ranges(xyz[:, 2], sub.n_views, sub.reproj)
            st.extent, st.box = _footprint(xyz)
        elif len(xyz) >= 50:               # a cloud growing tile by tile: its footprint grows
            _, (lo, hi) = _footprint(xyz)
            assert st.box is not None      # set with the first chunk
            lo, hi = np.minimum(st.box[0], lo), np.maximum(st.box[1], hi)
            st.box, st.extent = (lo, hi), float(max(np.max(hi - lo), 1e-6))
        return self._send(key, st, sub, xyz, visible, tuple(x.t_added for x in batches))

    def _send(self, key, st: _Cloud, sub: PointBatch, xyz: np.ndarray, visible: bool,
              t_added: tuple[float, ...]) -> int:
        g, kind = key
        name = f"/recon/g{g}/{kind}/chunk_{st.next_k}"
        st.next_k += 1
        colors = point_colors(self.settings.color_mode, sub.rgb, xyz[:, 2], sub.n_views,
                              sub.reproj, st.ranges)
        h = self.scene.add_point_cloud(name, xyz.astype(np.float32), colors,
                                       point_size=self.point_size(), precision="float32",
                                       point_shape="rounded", point_shading="flat",
                                       visible=visible)
        now = time.time()
        st.chunks.append(_Chunk(h, xyz, sub, now, t_added))
        self.sent_log.append({"name": name, "n": len(sub), "t_sent": now, "t_added": t_added,
                              "bytes": int(xyz.nbytes + colors.nbytes)})
        return len(sub)

    def point_size(self, n_shown: int | None = None) -> float:
        """Point size in scene units: the setting times the automatic size, at which the points
        shown (or n_shown) about tile the footprint of the clouds shown (display.auto_point_size)."""
        live = [c for (g, kind), c in self._clouds.items() if c.generation >= 0 and self._shows(kind)]
        ext = max((c.extent for c in live), default=1000.0)
        area = union_area([c.box for c in live if c.box is not None])
        n = self._shown() if n_shown is None else n_shown
        return float(self.settings.point_size * auto_point_size(ext, area, n))

    def apply_point_size(self, size: float | None = None) -> None:
        size = self.point_size() if size is None else size
        for st in self._clouds.values():
            for c in st.chunks:
                c.handle.point_size = size
        moving = self.moving_points()
        if moving:
            size = self.point_size(moving)
            for st in self._clouds.values():
                if st.moving is not None:
                    st.moving.handle.point_size = size

    def apply_colors(self) -> None:
        for st in self._clouds.values():
            for c in st.chunks:
                c.handle.colors = point_colors(self.settings.color_mode, c.batch.rgb, c.xyz[:, 2],
                                               c.batch.n_views, c.batch.reproj, st.ranges)
        # the moving subsamples: rebuilt in the new colours when the next gesture starts

    def _chunks_visible(self, kind: str, st: _Cloud) -> bool:
        """Are a cloud's chunks drawn (its kind shown, and no moving subsample drawn instead)?"""
        return self._shows(kind) and not (self.moving and st.moving is not None)

    def apply_visibility(self) -> None:
        for (g, kind), st in self._clouds.items():
            chunks = self._chunks_visible(kind, st)
            for c in st.chunks:
                c.handle.visible = chunks
            if st.moving is not None:
                st.moving.handle.visible = self._shows(kind) and self.moving
        self.apply_point_size()          # the points shown set the size

    # -- while a view moves (motion.py) -------------------------------------------------------
    def set_moving(self, moving: bool, budget: int | None) -> None:
        """Draw each cloud from its moving subsample (`budget` points in all, None: as shown)
        while a view moves, or from its chunks again."""
        self.moving, self.moving_budget = moving, budget
        if not (moving and self.sync_moving()):      # a rebuild applies the visibility itself
            self.apply_visibility()

    def moving_fraction(self) -> float | None:
        """The fraction of the points shown that is drawn while a view moves (None: all)."""
        shown = self._shown()
        if self.moving_budget is None or shown <= self.moving_budget:
            return None
        return self.moving_budget / float(shown)

    def moving_points(self) -> int:
        """Points drawn while a view moves, with the subsamples as they are now built."""
        return sum(st.moving.n if st.moving is not None else sum(len(c.batch) for c in st.chunks)
                   for (g, kind), st in self._clouds.items() if self._shows(kind))

    def _moving_key(self, st: _Cloud, f: float) -> tuple:
        return (st.generation, st.next_k, len(st.chunks), round(f, 6), self.settings.color_mode)

    def sync_moving(self) -> bool:
        """Build (or drop) each cloud's moving subsample to match its chunks and the budget: the
        points of its chunks whose hash falls below the moving fraction (display.keep_mask, nested
        in the chunks' own subsample), coloured as they are. Returns whether anything changed."""
        f = self.moving_fraction()
        changed = False
        for key, st in self._clouds.items():
            if f is None or not st.chunks:
                if st.moving is not None:
                    st.moving.handle.remove()
                    st.moving, changed = None, True
                continue
            mk = self._moving_key(st, f)
            if st.moving is not None and st.moving.key == mk:
                continue
            parts = []
            for c in st.chunks:
                m = keep_mask(c.batch.ids, st.fraction * st.kept * f, cloud_salt(*key))
                parts.append((c.xyz[m], c.batch.subset(m)))
            xyz = np.concatenate([p[0] for p in parts]) if parts else np.zeros((0, 3))
            sub = concat_batches(tuple(p[1] for p in parts))
            if st.moving is not None:
                st.moving.handle.remove()
            colors = point_colors(self.settings.color_mode, sub.rgb, xyz[:, 2], sub.n_views,
                                  sub.reproj, st.ranges)
            h = self.scene.add_point_cloud(f"/recon/g{key[0]}/{key[1]}/moving", xyz.astype(np.float32),
                                           colors, point_size=self.point_size(), precision="float32",
                                           point_shape="rounded", point_shading="flat",
                                           visible=self.moving and self._shows(key[1]))
            st.moving, changed = _Moving(h, len(xyz), mk), True
        if changed:
            self.apply_visibility()
        return changed

    def _nearest(self, ray_origin, ray_direction, max_angle: float):
        """(group, cloud state, display xyz) of the displayed point nearest in angle to a ray."""
        best = None
        d = np.asarray(ray_direction, float)
        d = d / np.linalg.norm(d)
        for (g, kind), st in self._clouds.items():
            if st.transform is None or not self._shows(kind):
                continue
            for ch in st.chunks:
                k = closest_point_to_ray(ch.xyz, ray_origin, ray_direction, max_angle=max_angle)
                if k is None:
                    continue
                v = ch.xyz[k] - np.asarray(ray_origin, float)
                ang = np.linalg.norm(np.cross(v, d)) / max(v @ d, 1e-12)
                if best is None or ang < best[0]:
                    best = (ang, g, st, np.asarray(ch.xyz[k], float))
        return None if best is None else best[1:]

    def nearest_point(self, ray_origin, ray_direction, max_angle: float = 0.02
                      ) -> tuple[int, np.ndarray] | None:
        """(group, affine xyz) of the displayed point nearest in angle to a click ray (within
        max_angle radians), or None: the scene answers picks on its own clouds."""
        got = self._nearest(ray_origin, ray_direction, max_angle)
        if got is None:
            return None
        g, st, xyz = got
        assert st.transform is not None      # _nearest skips a cloud without one
        return g, st.transform.inverse(xyz[None])[0]

    def nearest_display_point(self, ray_origin, ray_direction, max_angle: float = 0.02
                              ) -> np.ndarray | None:
        """The displayed point (display coordinates) nearest in angle to a ray, or None."""
        got = self._nearest(ray_origin, ray_direction, max_angle)
        return None if got is None else got[2]

    def _shows(self, kind: str) -> bool:
        """Are the clouds of this kind (sparse, dense) shown?"""
        return self.settings.show_sparse if kind == "sparse" else self.settings.show_dense

    def _shown(self) -> int:
        """Points on screen: the chunks of the kinds shown."""
        return sum(len(c.batch) for (g, kind), st in self._clouds.items() if self._shows(kind)
                   for c in st.chunks)

    def displayed_points(self) -> int:
        return sum(len(c.batch) for st in self._clouds.values() for c in st.chunks)

    def bounds(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(min, max) of the displayed points (2nd-98th percentiles), or None."""
        pts = [c.xyz for st in self._clouds.values() for c in st.chunks if len(c.xyz)]
        if not pts:
            return None
        P = np.concatenate(pts)
        return np.percentile(P, 2, axis=0), np.percentile(P, 98, axis=0)

    # -- tiles --------------------------------------------------------------------------------
    def tile_mode(self, dense: bool) -> str:
        """The drawing of a group's tiles: the setting, with `auto` resolved (`dense`: the
        group has dense points)."""
        mode = self.settings.tiles
        if mode == "auto":
            return "outlines" if dense and self.settings.show_dense else "textured"
        return mode

    def _sync_tiles(self, g: int, tiles: dict[str, TileView], newest: str | None,
                    T: DisplayTransform, dense: bool = False) -> None:
        mode = self.tile_mode(dense)
        changed = mode != self._tile_mode.get(g)
        if changed:
            for (gg, _), node in self._tiles.items():
                if gg == g and node.image is not None:
                    node.image.visible = mode == "textured"
        self._tile_mode[g] = mode
        side = 160 if len(tiles) <= 100 else 96          # texture budget for many tiles
        for tid, tv in tiles.items():
            node = self._tiles.get((g, tid))
            if node is not None and node.version == tv.version and node.transform is T \
                    and (node.image is not None or mode != "textured"):
                continue
            changed = True
            corners = T.apply(tv.footprint).astype(np.float64)
            diag = float(np.linalg.norm(corners[2] - corners[0]))
            if node is not None and np.max(np.abs(corners - node.corners)) < 0.005 * diag \
                    and (node.image is not None or mode != "textured"):
                node.version, node.transform = tv.version, T
                continue
            self._tiles[(g, tid)] = self._draw_tile(g, tv, corners, T, mode, node, side)
        if changed:
            self._draw_outlines(g, mode)
        self._sync_newest(g, tiles, newest, T)

    def _draw_tile(self, g: int, tv: TileView, corners: np.ndarray, T: DisplayTransform,
                   mode: str, old: _TileNode | None, side: int) -> _TileNode:
        """A tile's node: its corners (outlined with its group's, `_draw_outlines`) and textured
        quad (moved when only its pose changed, re-textured when its shape changed)."""
        base = f"/recon/g{g}/tiles/{safe_name(tv.tile_id)}"
        col = tuple(int(c) for c in PALETTE[self.image_index.get(tv.image, 0) % len(PALETTE)])
        diag = float(np.linalg.norm(corners[2] - corners[0]))
        image, frame = (old.image, old.frame) if old is not None else (None, None)
        if mode != "textured" and image is not None:   # hidden at a pose now stale: drop it
            image.remove()
            image, frame = None, None
        if mode == "textured":
            lowered = corners + np.array([0.0, 0.0, -0.02 * diag])   # just under the points
            new = quad_frame(lowered)
            if image is not None and frame is not None and new.similar(frame):
                image.position = tuple(new.centre)
                image.wxyz = tuple(new.wxyz)
                frame = QuadFrame(new.a, new.b, new.n, frame.top, frame.shear, frame.height,
                                  frame.xmin, frame.bw, frame.bh, new.centre)
            else:
                image, frame = self._tile_image(base, tv, lowered, side)
        return _TileNode(tv.version, T, corners, col, image, frame)

    def _draw_outlines(self, g: int, mode: str) -> None:
        """Every registered tile's outline of a group in one node, coloured by image (one draw
        call where one per tile cost software WebGL ~1 ms each: bench_viewer.py --fps)."""
        nodes = [n for (gg, _), n in sorted(self._tiles.items()) if gg == g]
        if not nodes:
            old = self._outlines.pop(g, None)
            if old is not None:
                old.remove()
            return
        corners = np.stack([n.corners for n in nodes])                     # (T, 4, 3)
        seg = np.stack([corners, np.roll(corners, -1, axis=1)], axis=2)     # (T, 4, 2, 3)
        cols = np.broadcast_to(np.array([n.color for n in nodes], np.uint8)[:, None, None, :],
                               (len(nodes), 4, 2, 3))
        self._outlines[g] = self.scene.add_line_segments(
            f"/recon/g{g}/tiles/outlines", seg.reshape(-1, 2, 3).astype(np.float32),
            np.ascontiguousarray(cols.reshape(-1, 2, 3)), thickness=1.5, thickness_units="screen",
            visible=mode != "hidden")

    def _tile_image(self, base: str, tv: TileView, corners: np.ndarray, side: int
                    ) -> tuple[viser.ImageHandle | None, QuadFrame | None]:
        tile = self.tile_windows.get(tv.tile_id)
        if tile is None or tile.image not in self.images.images:
            return None, None
        q = quad_image(corners, self.images.read(tile, side), max_side=side)
        q.rgba[..., 3] = np.where(q.rgba[..., 3] > 0, 215, 0)
        h = self.scene.add_image(f"{base}/image", q.rgba, q.render_width, q.render_height,
                                 format="png", wxyz=q.wxyz, position=q.position,
                                 cast_shadow=False, receive_shadow=False)
        return h, quad_frame(corners)

    def _sync_newest(self, g: int, tiles: dict[str, TileView], newest: str | None,
                     T: DisplayTransform) -> None:
        if newest is None or newest not in tiles:
            return
        tv = tiles[newest]
        key = (newest, tv.version, id(T))
        if self._newest.get(g) == key:
            return
        self._newest[g] = key
        corners = T.apply(tv.footprint).astype(np.float64)
        lift = np.array([0.0, 0.0, 0.01 * float(np.linalg.norm(corners[2] - corners[0]))])
        seg = np.stack([corners + lift, np.roll(corners + lift, -1, axis=0)], axis=1).astype(np.float32)
        line = self.scene.add_line_segments(f"/recon/g{g}/tiles/newest", seg, NEWEST, thickness=4.0,
                                            thickness_units="screen")
        label = self.scene.add_label(f"/recon/g{g}/tiles/newest_label",
                                     f"{newest} (#{tv.order + 1})", position=tuple(corners[0] + lift),
                                     anchor="bottom-left", visible=not self.finished)
        self._newest_nodes[g] = (line, label)

    def finish(self) -> None:
        """The run is over: drop the newest-tile labels (the outlines stay highlighted)."""
        if self.finished:
            return
        self.finished = True
        for line, label in self._newest_nodes.values():
            label.visible = False

    def tile_nodes(self) -> list:
        """The nodes that draw the registered tiles (outlines, textured quads, the newest)."""
        return ([h for h in self._outlines.values()] + [n.image for n in self._tiles.values() if n.image is not None]
                + [line for line, _ in self._newest_nodes.values()])

    def label_nodes(self) -> list:
        return [label for _, label in self._newest_nodes.values()]

    def set_tiles_visible(self, visible: bool) -> None:
        for line, label in self._newest_nodes.values():
            line.visible = visible
            label.visible = visible and not self.finished

    def clear(self) -> None:
        """Remove every reconstruction node (used when the frame changes wholesale)."""
        for st in self._clouds.values():
            for c in st.chunks:
                c.handle.remove()
            if st.moving is not None:
                st.moving.handle.remove()
        self._clouds.clear()
        for node in self._tiles.values():
            if node.image is not None:
                node.image.remove()
        self._tiles.clear()
        for h in self._outlines.values():
            h.remove()
        self._outlines.clear()
        for line, label in self._newest_nodes.values():
            line.remove()
            label.remove()
        self._newest_nodes.clear()
        self._newest.clear()
        self._tile_mode.clear()


def tile_windows_for(images: list, tile_size: int, overlap: int | None) -> dict[str, Window]:
    """Windows of every tile of the images (recon_core.model.tiling), keyed by tile id."""
    from recon_core.model.tiling import tile_image

    out = {}
    for im in images:
        for t in tile_image(im.name, im.width, im.height, tile_size, overlap):
            out[t.id] = t
    return out
