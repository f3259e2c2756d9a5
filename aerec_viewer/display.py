"""Pure display maths of the viewer: frame-to-scene transforms, point colours, decimation, rays.

Nothing here imports viser, so everything is tested directly.

Display coordinates are what the scene receives: float32, small numbers, z up. Two frames exist:
- the affine frame of a date group (arbitrary 3D affine gauge: the canonical gauge makes its z
  axis nearly parallel to y). It is shown through a fixed `DisplayTransform` computed once from
  the first points and the first registered camera: horizontal axes = (column, -row) of that
  camera's image, in pixels, relative to the centre of the first points; vertical axis = offset
  from the points' best-fit plane, scaled so that the relief spans a fixed fraction of the width.
  An affine frame has no metric and, for affine cameras, a depth-reversal (Necker) ambiguity:
  relief may show inverted until the Euclidean upgrade.
- the Euclidean frame after the upgrade: local ENU metres (z up) relative to the ENU origin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.evaluation.colormap import sequential
from recon_core.geometry.camera import AffineCamera
from recon_core.geometry.enu_map import BendWarp, EnuMap, EnuWarp

COLOR_MODES = ("image colour", "height", "number of views", "reprojection error")


# -- transforms -----------------------------------------------------------------------------
@dataclass(frozen=True)
class DisplayTransform:
    """y = A @ (x + warp(x)) + b, x_display = y + post(y), mapping a frame (affine or ENU) to
    scene coordinates (warp: the upgrade's metric bend step, recon_core.bend.metric;
    post: the bend fitted to control GCPs, recon_core.bend.gcp; each None when not
    applied).

    Attributes:
        A: (3, 3) linear part; b: (3,) offset.
        kind: "affine" or "euclidean".
        label: one-line description of the frame for the panel.
        z_scale: vertical exaggeration applied (1 in the Euclidean frame).
        camera: for the affine frame, the 2 x 3 linear part of the camera whose image axes
            are the horizontal axes.
    """

    A: np.ndarray
    b: np.ndarray
    kind: str
    label: str
    z_scale: float = 1.0
    camera: np.ndarray | None = None     # (2, 3) camera rows of the horizontal axes (affine)
    warp: BendWarp | None = None     # X -> D(X) (n, 3), applied before A
    post: EnuWarp | None = None      # Y -> G(Y) (n, 3), applied after A and b

    def apply(self, X: np.ndarray) -> np.ndarray:
        """(n, 3) frame points -> (n, 3) float32 display points."""
        X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
        if self.warp is not None and len(X):
            X = X + self.warp(X)
        Y = X @ self.A.T + self.b
        if self.post is not None and len(Y):
            Y = Y + self.post(Y)
        return Y.astype(np.float32)

    def inverse(self, Y: np.ndarray) -> np.ndarray:
        """(n, 3) display points -> (n, 3) float64 frame points: the same map as the upgrade's
        (recon_core.geometry.enu_map.EnuMap, H = [A | b]), undone as it undoes it."""
        return EnuMap(np.hstack([self.A, self.b[:, None]]), self.warp, self.post).inverse(Y)


def _robust_span(v: np.ndarray) -> float:
    lo, hi = np.percentile(v, [5.0, 95.0])
    return float(hi - lo)


def affine_display_transform(X: np.ndarray, camera: np.ndarray, *,
                             relief_fraction: float = 0.15,
                             centre: np.ndarray | None = None) -> DisplayTransform:
    """Display transform of an affine frame from its points and its first registered camera.

    Args:
        X: (n, 3) affine points (n >= 3).
        camera: (2, 4) affine camera of the first registered tile (full-image pixels).
        relief_fraction: robust height span shown as this fraction of the robust width.
        centre: affine point put at the display origin (default: the points' median).
    Returns:
        A transform with det(A) > 0 (not mirrored) whose x, y are (col, -row) pixels of
        `camera`'s image relative to the centre and whose z is the scaled offset from the
        points' best-fit plane.
    """
    X = np.asarray(X, dtype=np.float64).reshape(-1, 3)
    M = AffineCamera.from_array(camera).linear
    c = np.median(X, axis=0) if centre is None else np.asarray(centre, dtype=np.float64)
    _, _, vt = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    normal = vt[-1]
    h = (X - c) @ normal
    rows = np.vstack([M[0], -M[1]])
    width = max(_robust_span((X - c) @ rows[0]), _robust_span((X - c) @ rows[1]), 1e-9)
    k = relief_fraction * width / max(_robust_span(h), 1e-9 * width)
    A = np.vstack([rows, k * normal])
    if abs(np.linalg.det(np.vstack([rows, normal]))) < 0.02 * np.prod(np.linalg.norm(rows, axis=1)):
        return _pca_display_transform(X, c)          # ground plane seen edge-on: fall back
    if np.linalg.det(A) < 0:
        A[2] *= -1.0
    label = (f"affine frame (no metric): x, y = column, -row of the first tile's image (px); "
             f"z = offset from the best-fit plane, relief scaled to "
             f"{100 * relief_fraction:.0f} % of the width; may be depth-reversed")
    return DisplayTransform(A, -A @ c, "affine", label, float(k), M.copy())


def refine_affine_transform(T: DisplayTransform, X: np.ndarray) -> DisplayTransform:
    """Same horizontal axes and origin, vertical axis re-fitted to a larger cloud X.

    The first points (the initial tile pair) see little of the site: their plane and relief
    span give a poor vertical scale. The viewer refits it when a whole new model arrives
    (after a global bundle adjustment), when every node is resent anyway.
    """
    if T.kind != "affine" or T.camera is None or len(X) < 20:
        return T
    centre = np.linalg.solve(T.A, -T.b)
    return affine_display_transform(X, np.hstack([T.camera, np.zeros((2, 1))]), centre=centre)


def _pca_display_transform(X: np.ndarray, c: np.ndarray) -> DisplayTransform:
    """Whitened principal axes, third axis at 15 % of the first (fallback for degenerate views)."""
    _, s, vt = np.linalg.svd(X - X.mean(axis=0), full_matrices=False)
    scale = 100.0 / max(s[0] / np.sqrt(len(X)), 1e-12)
    A = vt * scale
    A[2] *= 0.15 * s[0] / max(s[2], 1e-12)
    if np.linalg.det(A) < 0:
        A[2] *= -1.0
    return DisplayTransform(A, -A @ c, "affine", "affine frame (no metric): principal axes, "
                            "whitened; relief exaggerated; may be depth-reversed", 1.0)


def euclidean_display_transform(H: np.ndarray, origin_llh: np.ndarray, warp: BendWarp | None = None,
                                post: EnuWarp | None = None) -> DisplayTransform:
    """Display of the Euclidean frame: ENU metres at the local origin, z up (A = H_A[:3, :3],
    after the metric bend step's warp and before the bend fitted to GCPs when there are: the
    same map as the DSM's)."""
    H = np.asarray(H, dtype=np.float64)
    lon, lat, h = (float(v) for v in origin_llh)
    label = (f"Euclidean frame: ENU metres, z up, origin lon {lon:.6f} lat {lat:.6f} "
             f"h {h:.1f} m (WGS84)")
    return DisplayTransform(H[:3, :3].copy(), H[:3, 3].copy(), "euclidean", label, 1.0, warp=warp,
                            post=post)


def image_footprint(T: DisplayTransform, camera: np.ndarray, width: int, height: int,
                    z: float = 0.0) -> np.ndarray:
    """(4, 3) display points on the plane z_display = z that `camera` sees at the corners of
    its width x height image (what the whole image covers, before the cloud is complete)."""
    cam = AffineCamera.from_array(camera)
    Ainv = np.linalg.inv(T.A)
    # pixel = linear @ Ainv @ (Y - b) + offset, Y = (x, y, z): linear in (x, y)
    M = cam.linear @ Ainv
    corners = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5],
                        [-0.5, height - 0.5]])
    rhs = corners - (cam.offset + M @ (np.array([0.0, 0.0, z]) - T.b))
    xy = np.linalg.solve(M[:, :2], rhs.T).T
    return np.column_stack([xy, np.full(4, z)])


# -- decimation -----------------------------------------------------------------------------
def keep_mask(ids: np.ndarray, fraction: float, salt: int = 0) -> np.ndarray:
    """Deterministic subsample: point id -> kept when its hash falls below `fraction`.

    The hash is splitmix64's finaliser of (id, salt): uniform, and independent across salts.
    Lowering the fraction only removes points (nested subsets), so a display can shrink without
    reshuffling, and a subsample of a subsample taken with the same salt is a subsample.
    """
    if fraction >= 1.0:
        return np.ones(len(ids), bool)
    with np.errstate(over="ignore"):
        z = np.asarray(ids, dtype=np.uint64) + np.uint64((salt * 0x9E3779B97F4A7C15) % (1 << 64))
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    return (z >> np.uint64(40)).astype(np.float64) / float(1 << 24) < fraction


def cloud_salt(group: int, kind: str) -> int:
    """The hash salt of one point cloud (store thinning and display share it)."""
    return 1 + 2 * group + (0 if kind == "sparse" else 1)


def auto_point_size(extent: float, area: float, n_shown: int) -> float:
    """Point size (scene units) at which the displayed points about tile the cloud's footprint:
    the mean spacing sqrt(area / n), never more than 1/200 of the extent (a sparse cloud), and
    quantised to steps of 2^(1/4) so a growing cloud resizes its points seldom.

    Drawing cost in software WebGL is the fragments: points of a fixed 1/200 of the extent
    cover a 600 m site about four times over at 150 k points (2 fps while orbiting, measured);
    points the size of their spacing cover it about once, whatever the budget."""
    cap = extent / 200.0
    if n_shown <= 0 or not area > 0:
        return cap
    size = float(np.sqrt(area / n_shown))
    if size >= cap:
        return cap
    q = 2.0 ** (np.round(4.0 * np.log2(size)) / 4.0)
    return float(min(cap, q))


def display_fraction(n_total: int, budget: int) -> float:
    """Fraction of points to display for a point budget."""
    return 1.0 if n_total <= budget else budget / float(n_total)


# -- colours --------------------------------------------------------------------------------
@dataclass(frozen=True)
class ColorRanges:
    """Value ranges of the colour maps, fixed at each display rebuild."""

    z: tuple[float, float] = (0.0, 1.0)
    views: tuple[float, float] = (2.0, 6.0)
    reproj: tuple[float, float] = (0.0, 1.0)


def color_ranges(z: np.ndarray, n_views: np.ndarray, reproj: np.ndarray) -> ColorRanges:
    """Robust ranges (2nd-98th percentiles) of display height, views and reprojection error."""
    if len(z) == 0:
        return ColorRanges()
    zl, zh = np.percentile(z, [2.0, 98.0])
    rh = float(np.percentile(reproj, 98.0)) if len(reproj) else 1.0
    vh = float(max(3.0, np.max(n_views))) if len(n_views) else 6.0
    return ColorRanges((float(zl), float(max(zh, zl + 1e-6))), (2.0, vh), (0.0, max(rh, 1e-3)))


def point_colors(mode: str, rgb: np.ndarray, z: np.ndarray, n_views: np.ndarray,
                 reproj: np.ndarray, ranges: ColorRanges) -> np.ndarray:
    """(n, 3) uint8 colours of points for a colour mode of `COLOR_MODES`."""
    if mode == "height":
        return sequential(z, *ranges.z)
    if mode == "number of views":
        return sequential(n_views, *ranges.views)
    if mode == "reprojection error":
        return sequential(reproj, *ranges.reproj)
    return np.asarray(rgb, dtype=np.uint8).reshape(-1, 3)


# -- rays and planes ------------------------------------------------------------------------
def quat_to_matrix(wxyz: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) -> 3x3 rotation matrix."""
    w, x, y, z = np.asarray(wxyz, dtype=np.float64) / np.linalg.norm(wxyz)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    """3x3 rotation matrix -> unit quaternion (w, x, y, z) with w >= 0."""
    R = np.asarray(R, dtype=np.float64)
    K = np.array([[R[0, 0] - R[1, 1] - R[2, 2], R[1, 0] + R[0, 1], R[2, 0] + R[0, 2], R[2, 1] - R[1, 2]],
                  [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], R[2, 1] + R[1, 2], R[0, 2] - R[2, 0]],
                  [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], R[1, 0] - R[0, 1]],
                  [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]]]) / 3.0
    vals, vecs = np.linalg.eigh(K)
    x, y, z, w = vecs[:, np.argmax(vals)]
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


# A flat image plane seen from above: local x = display x, local y (image rows) = display -y.
FLAT_WXYZ = np.array([0.0, 1.0, 0.0, 0.0])


def plane_hit(ray_origin: np.ndarray, ray_direction: np.ndarray, *, position: np.ndarray,
              wxyz: np.ndarray, render_width: float, render_height: float
              ) -> tuple[float, float] | None:
    """Where a ray meets an image plane added by `scene.add_image`, as fractions of its size.

    In the node's local frame the image spans x in [-w/2, w/2] (left to right) and y in
    [-h/2, h/2] (top to bottom) on the plane z = 0 (measured: a clicked pixel comes back to
    1e-5 px). Returns (fx, fy) with (0, 0) the top-left corner and (1, 1) the bottom-right one,
    or None when the ray is parallel to the plane, points away from it, or misses the image.
    """
    R = quat_to_matrix(wxyz)
    o = R.T @ (np.asarray(ray_origin, dtype=np.float64) - np.asarray(position, dtype=np.float64))
    d = R.T @ np.asarray(ray_direction, dtype=np.float64)
    if abs(d[2]) < 1e-12:
        return None
    t = -o[2] / d[2]
    if t < 0:
        return None
    x, y = o[0] + t * d[0], o[1] + t * d[1]
    fx, fy = x / render_width + 0.5, y / render_height + 0.5
    eps = 1e-9
    if not (-eps <= fx <= 1.0 + eps and -eps <= fy <= 1.0 + eps):
        return None
    return float(min(max(fx, 0.0), 1.0)), float(min(max(fy, 0.0), 1.0))


def plane_point(fx: float, fy: float, *, position: np.ndarray, wxyz: np.ndarray,
                render_width: float, render_height: float, lift: float = 0.0) -> np.ndarray:
    """Inverse of `plane_hit`: (fx, fy) fractions -> display point (lifted along the normal)."""
    local = np.array([(fx - 0.5) * render_width, (fy - 0.5) * render_height, -lift])
    return quat_to_matrix(wxyz) @ local + np.asarray(position, dtype=np.float64)


def closest_point_to_ray(points: np.ndarray, ray_origin: np.ndarray, ray_direction: np.ndarray,
                         max_angle: float = 0.01) -> int | None:
    """Index of the point that appears closest to the clicked ray (smallest angle), or None.

    Only points in front of the origin and within `max_angle` radians of the ray count.
    """
    P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(P) == 0:
        return None
    d = np.asarray(ray_direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    v = P - np.asarray(ray_origin, dtype=np.float64)
    t = v @ d
    perp = np.linalg.norm(v - t[:, None] * d, axis=1)
    ang = np.where(t > 0, perp / np.maximum(t, 1e-12), np.inf)
    k = int(np.argmin(ang))
    return k if ang[k] <= max_angle else None


# -- quads ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class QuadImage:
    """A parallelogram textured with an image, as `scene.add_image` arguments."""

    rgba: np.ndarray              # (h, w, 4) uint8, transparent outside the parallelogram
    render_width: float
    render_height: float
    wxyz: np.ndarray
    position: np.ndarray


@dataclass(frozen=True)
class QuadFrame:
    """The plane frame of a parallelogram: in-plane axes a (along the top edge) and b, normal n,
    bounding rectangle (xmin, width bw, height bh) in (a, b) and its centre."""

    a: np.ndarray
    b: np.ndarray
    n: np.ndarray
    top: float           # |top edge|
    shear: float         # left edge's component along a
    height: float        # left edge's component along b
    xmin: float
    bw: float
    bh: float
    centre: np.ndarray

    @property
    def wxyz(self) -> np.ndarray:
        return matrix_to_quat(np.stack([self.a, self.b, self.n], axis=1))

    def similar(self, other: "QuadFrame", tol: float = 0.03) -> bool:
        """Same shape up to a rigid motion, within tol (relative)."""
        d = max(self.bw, self.bh)
        return (abs(self.top - other.top) < tol * d and abs(self.shear - other.shear) < tol * d
                and abs(self.height - other.height) < tol * d)


def quad_frame(corners: np.ndarray) -> QuadFrame:
    """Frame of the parallelogram corners (4, 3): top-left, top-right, bottom-right, bottom-left."""
    C = np.asarray(corners, dtype=np.float64)
    e1, e2 = C[1] - C[0], C[3] - C[0]
    a = e1 / np.linalg.norm(e1)
    b = e2 - (e2 @ a) * a
    b /= np.linalg.norm(b)
    n = np.cross(a, b)
    L1, s, t = float(np.linalg.norm(e1)), float(e2 @ a), float(e2 @ b)
    xmin, xmax = min(0.0, s), max(L1, L1 + s)
    bw, bh = xmax - xmin, t
    return QuadFrame(a, b, n, L1, s, t, xmin, bw, bh, C[0] + a * (xmin + bw / 2) + b * (bh / 2))


def quad_image(corners: np.ndarray, tex: np.ndarray, max_side: int = 192) -> QuadImage:
    """Texture the parallelogram corners (4, 3) (top-left, top-right, bottom-right, bottom-left
    of the tile, in display coordinates) with `tex` (h, w), (h, w, 3) or (h, w, 4) uint8.

    `add_image` draws rectangles; the parallelogram is drawn as the bounding rectangle in its
    plane with the texture warped in and the outside transparent.
    """
    import cv2

    f = quad_frame(corners)
    L1, s, t, xmin, bw, bh = f.top, f.shear, f.height, f.xmin, f.bw, f.bh
    scale = max_side / max(bw, bh)
    W, Hh = max(2, int(round(bw * scale))), max(2, int(round(bh * scale)))
    tex = np.asarray(tex)
    if tex.ndim == 2:
        tex = np.repeat(tex[..., None], 3, axis=2)
    th, tw = tex.shape[:2]
    alpha = tex[..., 3] if tex.shape[2] == 4 else np.full((th, tw), 255, np.uint8)
    # dst pixel (u, v) -> plane (x, y) = (xmin + (u + .5) bw / W, (v + .5) bh / H);
    # plane (x, y) = p e1' + q e2' with e1' = (L1, 0), e2' = (s, t) -> tex pixel (p tw - .5, q th - .5)
    Binv = np.linalg.inv(np.array([[L1, s], [0.0, t]]))
    S = np.diag([tw, th]) @ Binv @ np.array([[bw / W, 0.0], [0.0, bh / Hh]])
    off = np.diag([tw, th]) @ Binv @ np.array([xmin + 0.5 * bw / W, 0.5 * bh / Hh]) - 0.5
    M = np.hstack([S, off[:, None]])
    rgba = np.dstack([tex[..., :3], alpha])
    out = cv2.warpAffine(rgba, M, (W, Hh), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=(0, 0, 0, 0))
    return QuadImage(out, float(bw), float(bh), f.wxyz, f.centre)
