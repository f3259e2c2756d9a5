"""Where a GCP should be in an image it has not been placed in yet, from where it was placed.

1. Its 3D point in the group's affine frame: triangulated from >= 2 usable observations, or,
   from a single one, where the pixel's viewing ray meets the sparse surface (the median depth
   along the ray of the sparse points that project within a few pixels of the click).
2. Projected by the registered tile of the target image that contains it: the prediction.
3. Refined by matching: the patch around the observation in the source image against the target
   image warped into the source's geometry by the local affine map between the two images (fitted
   to the same nearby sparse points), normalised cross-correlation over a small search window,
   sub-pixel by a parabola through the peak. The refinement is kept only when the correlation is
   clear (score and margin); otherwise the geometric prediction stands.

Once the group has a Euclidean upgrade, a GCP's surveyed position predicts it too, as a
georeferenced model does in Metashape (`predict_from_ground`): its ENU position through the
inverse of the group's upgrade map to the affine frame, projected as in 2. That needs no
observation at all; where the GCP has fewer than two, it is the one to show (`predict_gcp`).
The gap between an observation and this prediction is what the GCP's error in the upgrade is.

Part of the core (no display here): the viewer's GCP panel calls `predict_gcp` and shows the
result for the operator to accept or adjust; any other front end (a script, a CLI) can too.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from recon_core.euclidean.georef import triangulate_gcp
from recon_core.geometry.enu_map import EnuMap
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.site import ImageInfo, read_window

# Prediction.source: from the GCP's observations in the group's other images, or from its
# surveyed position through the group's upgrade
FROM_OBSERVATIONS = "observations"
FROM_SURVEY = "surveyed"
SURVEYED_HOW = "from its surveyed position, through the upgrade"


@dataclass(frozen=True)
class Prediction:
    image: str
    col: float                      # the prediction to show (refined when the match is clear)
    row: float
    geometric: tuple[float, float]  # from the 3D point alone
    score: float | None             # NCC of the refinement (None: not refined)
    how: str                        # plain words: from what, refined or why not
    reach_px: float | None = None   # triangulated: the observations' reprojection RMS (px), how
                                    # well they agree. From one observation none: the spread of
                                    # the nearby sparse depths did not predict the error (measured
                                    # on `tiny`: 17 px stated for 1 px off, 0.3 px for 45 px off)
    source: str = FROM_OBSERVATIONS  # FROM_OBSERVATIONS or FROM_SURVEY (predict_from_ground)

    def uncertainty(self) -> str:
        """Plain words for the panel: how well the observations it comes from agree, how far
        matching moved it, that it is as good as the upgrade, or that nothing tells how far off
        it is."""
        if self.source == FROM_SURVEY:
            return "as far off as the upgrade's error at this GCP: check it in the loupe"
        parts = []
        if self.reach_px is not None:
            parts.append(f"its observations agree to {max(self.reach_px, 0.1):.1f} px")
        if self.score is not None:
            moved = float(np.hypot(self.col - self.geometric[0], self.row - self.geometric[1]))
            parts.append(f"matching moved it {moved:.1f} px")
        return ", ".join(parts) or "from one observation: check it in the loupe"

    @property
    def confirmed(self) -> bool:
        """Triangulated from >= 2 observations, or refined by a clear match: good enough to
        record without the operator looking (Place it in its other images)."""
        return self.score is not None or self.how.startswith("triangulated")


def _tile_camera(model, image: str, cr) -> int | None:
    """Index of the registered tile of `image` containing pixel cr, nearest its centre."""
    tiles = model.tiles_at(image, cr)
    if not tiles:
        return None
    return min(tiles, key=lambda t: float(np.hypot(*(np.asarray(cr, float) - model.tiles[t].centre))))


def _project(model, t: int, X: np.ndarray) -> np.ndarray:
    """Pixels of points X in tile t as the image sees them: the tile camera's projection plus
    the SfM's within-tile correction there (what the camera was fitted to is pixel - correction)."""
    p = model.camera(t).project(X)
    return p + model.correction_at(t, p)


def _project_in_image(model, image: str, X: np.ndarray) -> tuple[int, np.ndarray] | None:
    """(the registered tile of `image` that sees the affine point X (3,), X's pixel by that
    tile): projected by any registered tile of the image first, then by the one that contains
    that projection, once more when the pixel then falls outside it; None when the image has
    no registered tile there. The pixel may still lie outside the tile (the caller checks
    when it matters: model.tiles[t].contains)."""
    cand = [t for t, tile in enumerate(model.tiles) if tile.image == image and model.registered[t]]
    if not cand:
        return None
    guess = _project(model, cand[0], X[None])[0]
    t = _tile_camera(model, image, guess)
    if t is None:
        return None
    p = _project(model, t, X[None])[0]
    if not model.tiles[t].contains(p[None])[0]:
        t = _tile_camera(model, image, p)
        if t is None:
            return None
        p = _project(model, t, X[None])[0]
    return t, p


def _near_ray(model, t: int, cr, radius_px: float) -> np.ndarray:
    """Ids of sparse points projecting within radius_px of cr in tile t's camera."""
    ids = np.flatnonzero(model.has_point)
    uv = _project(model, t, model.X[ids])
    d = np.hypot(uv[:, 0] - cr[0], uv[:, 1] - cr[1])
    return ids[d < radius_px]


def point_from_one_observation(model, image: str, cr, radius_px=(6.0, 12.0, 25.0, 50.0)
                               ) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]] | None:
    """(3D point on the pixel's ray at the sparse surface, ids of the sparse points used, the
    stretch of the ray those points span: (its two ends))."""
    t = _tile_camera(model, image, cr)
    if t is None:
        return None
    P = model.cams[t]
    M, off = P[:, :3], P[:, 3]
    d = np.cross(M[0], M[1])                       # the viewing direction (M d = 0)
    X0 = np.linalg.lstsq(M, np.asarray(cr, float) - off, rcond=None)[0]   # a point on the ray
    for r in radius_px:
        ids = _near_ray(model, t, cr, r)
        if len(ids) >= 5:
            s = (model.X[ids] - X0) @ d / (d @ d)
            lo, mid, hi = np.percentile(s, [5, 50, 95])
            return X0 + float(mid) * d, ids, (X0 + float(lo) * d, X0 + float(hi) * d)
    return None


def _local_affine(model, ids, ta: int, tb: int) -> np.ndarray | None:
    """2 x 3 affine map from source to target pixels near the GCP (least squares on the sparse
    points `ids` projected by both tile cameras)."""
    if len(ids) < 6:
        return None
    a = _project(model, ta, model.X[ids])
    b = _project(model, tb, model.X[ids])
    A = np.hstack([a, np.ones((len(a), 1))])
    return np.linalg.lstsq(A, b, rcond=None)[0].T


def _parabola(v_minus: float, v0: float, v_plus: float) -> float:
    den = v_minus - 2 * v0 + v_plus
    return 0.0 if abs(den) < 1e-12 else float(np.clip(0.5 * (v_minus - v_plus) / den, -0.5, 0.5))


def refine_by_matching(src: ImageInfo, src_cr, dst: ImageInfo, dst_cr, J: np.ndarray,
                       half: int = 12, search: int = 6, min_score: float = 0.7,
                       segment: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> tuple[tuple[float, float], float] | None:
    """Refine dst_cr by NCC of the source patch against the target warped into the source's
    geometry with the local linear map J (2 x 2, source px -> target px), over +-search px; with
    `segment` (two target pixels: where the ray's plausible depths project) only peaks within
    3 px of that epipolar stretch count. Returns ((col, row), score) or None when the match is
    not clear."""
    n = half + search
    sc, sr = float(src_cr[0]), float(src_cr[1])
    c0, r0 = int(round(sc)) - half, int(round(sr)) - half
    if c0 < 0 or r0 < 0 or c0 + 2 * half + 1 > src.width or r0 + 2 * half + 1 > src.height:
        return None
    tmpl = read_window(src, c0, r0, 2 * half + 1, 2 * half + 1)
    # target region that the warped search area covers
    grid = np.arange(-n, n + 1, dtype=np.float64)
    gx, gy = np.meshgrid(grid + (round(sc) - sc), grid + (round(sr) - sr))
    tx = dst_cr[0] + J[0, 0] * gx + J[0, 1] * gy
    ty = dst_cr[1] + J[1, 0] * gx + J[1, 1] * gy
    x0, y0 = int(np.floor(tx.min())) - 1, int(np.floor(ty.min())) - 1
    x1, y1 = int(np.ceil(tx.max())) + 2, int(np.ceil(ty.max())) + 2
    if x0 < 0 or y0 < 0 or x1 > dst.width or y1 > dst.height:
        return None
    region = read_window(dst, x0, y0, x1 - x0, y1 - y0)
    if not (np.isfinite(tmpl).all() and np.isfinite(region).all()) or tmpl.std() < 1e-6:
        return None
    warped = cv2.remap(region.astype(np.float32), (tx - x0).astype(np.float32),
                       (ty - y0).astype(np.float32), cv2.INTER_LINEAR)
    raw = cv2.matchTemplate(warped, tmpl.astype(np.float32), cv2.TM_CCOEFF_NORMED)
    ncc = raw
    if segment is not None:             # keep the peaks near the epipolar stretch
        Ji = np.linalg.inv(J)
        a, b = (Ji @ (np.asarray(q, float) - np.asarray(dst_cr, float)) for q in segment)
        sy, sx = np.mgrid[-search:search + 1, -search:search + 1].astype(np.float64)
        ab = b - a
        tt = np.clip(((sx - a[0]) * ab[0] + (sy - a[1]) * ab[1]) / max(ab @ ab, 1e-12), 0.0, 1.0)
        dist = np.hypot(sx - a[0] - tt * ab[0], sy - a[1] - tt * ab[1])
        ncc = np.where(dist <= 3.0, ncc, -1.0).astype(np.float32)
    iy, ix = np.unravel_index(int(np.argmax(ncc)), ncc.shape)
    best = float(ncc[iy, ix])
    if best < min_score or not (0 < ix < ncc.shape[1] - 1 and 0 < iy < ncc.shape[0] - 1):
        return None
    # ambiguity: another local maximum, away from this one, nearly as good
    peaks = (ncc >= cv2.dilate(ncc, np.ones((3, 3), np.uint8))) & (ncc > -1)
    yy, xx = np.nonzero(peaks)
    far = np.hypot(yy - iy, xx - ix) > 4
    if far.any() and best - float(ncc[yy[far], xx[far]].max()) < 0.05:
        return None
    # sub-pixel on the unmasked correlation (the band mask would pull the peak into the band)
    dx = ix - search + _parabola(raw[iy, ix - 1], best, raw[iy, ix + 1])
    dy = iy - search + _parabola(raw[iy - 1, ix], best, raw[iy + 1, ix])
    # a shift (dx, dy) in the source's geometry is J (dx, dy) in the target
    return (float(dst_cr[0] + J[0, 0] * dx + J[0, 1] * dy),
            float(dst_cr[1] + J[1, 0] * dx + J[1, 1] * dy)), best


def predict_observation(model, images: dict[str, ImageInfo], observations: dict,
                        target: str, refine: bool = True) -> Prediction | None:
    """Predict a GCP's pixel in `target` (an image of the model's group) from its observations
    in the group's other images; None when no usable observation or no registered tile of the
    target sees the point."""
    obs = {im: cr for im, cr in observations.items() if im != target and im in model.images}
    if not obs:
        return None
    ids, span = None, None
    reach = None
    how = ""                                 # how X was found (set with it)
    if len(obs) >= 2:
        tri = triangulate_gcp(model, obs)
        X = tri.xyz
        how = f"triangulated from {tri.n_images} images"
        reach = tri.reproj_rms_px
    else:
        X = None
    if X is None:
        for im, cr in sorted(obs.items()):
            got = point_from_one_observation(model, im, cr)
            if got is not None:
                X, ids, span = got
                how = f"from {im} and the sparse surface ({len(ids)} points)"
                break
    if X is None:
        return None
    got = _project_in_image(model, target, X)
    if got is None:                         # no registered tile of the target sees the point
        return None
    tb, p = got
    geometric = (float(p[0]), float(p[1]))
    if not refine or span is None:
        # triangulated from >= 2 images, the projection is already as good as the clicks
        # (~0.3 px on the synthetic sites): matching would add its own errors
        return Prediction(target, *geometric, geometric, None, how, reach)
    src, src_cr = min(obs.items(), key=lambda kv: kv[0])
    ta = _tile_camera(model, src, src_cr)
    if ids is None and ta is not None:
        ids = _near_ray(model, ta, src_cr, 40.0)
    A = None if ta is None or ids is None else _local_affine(model, ids, ta, tb)
    if A is None:
        return Prediction(target, *geometric, geometric, None, how + "; not refined (too few points nearby)",
                          reach)
    search, segment = 6, None
    if span is not None:                 # one observation: search along the ray's plausible depths
        segment = tuple(_project(model, tb, np.asarray(q)[None])[0] for q in span)
        # the search runs in the source's geometry: a target offset d is J^-1 d there
        Ji = np.linalg.inv(A[:, :2])
        reach = max(float(np.abs(Ji @ (q - p)).max()) for q in segment)
        search = int(np.clip(np.ceil(reach) + 4, 6, 48))
    got = refine_by_matching(images[src], src_cr, images[target], p, A[:, :2], search=search,
                             segment=segment)
    if got is None:
        return Prediction(target, *geometric, geometric, None, how + "; no clear match to refine it", reach)
    (c, r), score = got
    return Prediction(target, c, r, geometric, score, how + f"; refined by matching {src} (NCC {score:.2f})",
                      reach)


@dataclass(frozen=True)
class Surveyed:
    """A GCP's surveyed position and the upgrade of a group that carries it to that group's
    affine frame: what `predict_from_ground` needs besides the model."""

    llh: tuple[float, float, float]   # lon, lat (degrees), ellipsoidal height (m)
    emap: EnuMap                      # the group's whole upgrade (GroupUpgrade.map)
    frame: LocalFrame                 # the upgrade's local ENU frame


def predict_from_ground(model, emap: EnuMap, frame: LocalFrame, gcp_llh, target: str) -> Prediction | None:
    """A GCP's pixel in `target` (an image of the model's group) from its surveyed position
    gcp_llh (lon, lat, h): to local ENU in `frame`, through the inverse of the group's upgrade
    map `emap` to the affine frame, projected by the registered tile of the target that
    contains it. None when the target is not the model's or no registered tile contains the
    projection, or the position is too far off the site for the map's warps to be undone.
    Needs no observation: after an upgrade every GCP is predicted in every image,
    and an observation's distance to this prediction is the GCP's error in the upgrade, in
    pixels."""
    if target not in model.images:
        return None
    enu = frame.geodetic_to_enu(np.asarray(gcp_llh, np.float64).reshape(1, 3))
    X = emap.inverse(enu)[0]
    if not np.isfinite(X).all():            # far off the site: the upgrade's warps do not undo
        return None
    got = _project_in_image(model, target, X)
    if got is None:
        return None
    t, p = got
    if not model.tiles[t].contains(p[None])[0]:
        return None
    at = (float(p[0]), float(p[1]))
    return Prediction(target, *at, at, None, SURVEYED_HOW, source=FROM_SURVEY)


def n_usable(model, observations: dict, target: str | None = None) -> int:
    """How many of a GCP's observations (other than in `target`) the model can use: in an image
    of its group, where a registered tile contains the pixel."""
    return sum(1 for im, cr in observations.items()
               if im != target and im in model.images and model.tiles_at(im, cr))


def predict_gcp(model, images: dict[str, ImageInfo], observations: dict, target: str,
                surveyed: Surveyed | None = None, refine: bool = True) -> Prediction | None:
    """The prediction to show of a GCP in `target`: from its own observations in the group's
    other images when it has 2 or more usable ones there (triangulated: what the operator's
    clicks say), else, when the group has an upgrade (`surveyed`), from its surveyed position
    (predict_from_ground); else from its one observation (predict_observation), or None."""
    if surveyed is not None and n_usable(model, observations, target) < 2:
        got = predict_from_ground(model, surveyed.emap, surveyed.frame, surveyed.llh, target)
        if got is not None:
            return got
    return predict_observation(model, images, observations, target, refine=refine)


def observation_residuals(model, observations: dict) -> dict[str, tuple[float, float]]:
    """Per usable observation of a GCP (>= 2 images of the model's group), the pixel residual
    observed - reprojected of its triangulated affine point: what the residual vectors show.
    {} when it cannot be triangulated."""
    obs = {im: cr for im, cr in observations.items() if im in model.images}
    if len(obs) < 2:
        return {}
    tri = triangulate_gcp(model, obs)
    if tri.xyz is None:
        return {}
    out = {}
    for im, cr in obs.items():
        t = _tile_camera(model, im, cr)
        if t is None:
            continue
        p = _project(model, t, np.asarray(tri.xyz)[None])[0]
        out[im] = (float(cr[0] - p[0]), float(cr[1] - p[1]))
    return out


# A GCP placed by prediction must triangulate with its other observations within this many
# pixels: about twice the sparse reprojection RMS of the affine tile cameras (0.2-0.35 px on
# the synthetic and the real sites), and far below a wrong match (1-35 px measured by
# bench/bench_operator.py on matches that NCC alone accepted: a repeated roof, a roof corner
# whose patch straddles a depth step).
PLACE_RESIDUAL_PX = 0.5


def place_in_other_images(model, images: dict[str, ImageInfo], observed: dict,
                          tol_px: float = PLACE_RESIDUAL_PX
                          ) -> tuple[dict[str, Prediction], dict[str, str], dict[str, Prediction]]:
    """Where to record a GCP in the images of `model`'s group it is not observed in, from its
    operator's observations `observed` there: ({image: Prediction} to record, {image: why it is
    left to the operator}, {image left: its geometric prediction, where there is one, for the
    operator to look at}).

    1. Every other image is predicted from the operator's observations alone (independently).
    2. The confirmed ones (triangulated, or refined by a clear match) are triangulated together
       with the observations; if any of them then reprojects farther than tol_px, the matched
       predictions are all left to the operator (a wrong match is not always a weak one).
    3. Images still left are predicted again by triangulation from what was kept (>= 2 images).
    """
    placed: dict[str, Prediction] = {}
    left: dict[str, str] = {}
    hints: dict[str, Prediction] = {}
    targets = [im for im in model.images if im not in observed]
    for image in targets:
        pred = predict_observation(model, images, observed, image)
        if pred is not None:
            hints[image] = Prediction(image, *pred.geometric, pred.geometric, None,
                                      pred.how.split(";")[0] + "; not confirmed: look before accepting",
                                      pred.reach_px)
        if pred is None:
            left[image] = "no prediction (no registered tile holds it there)"
        elif not pred.confirmed:
            left[image] = f"not confirmed by matching ({pred.how})"
        else:
            placed[image] = pred
    matched = [im for im, p in placed.items() if p.score is not None]
    if matched:
        res = observation_residuals(model, {**observed, **{im: (p.col, p.row) for im, p in placed.items()}})
        worst = max((float(np.hypot(*v)) for v in res.values()), default=np.inf)
        if not worst <= tol_px:
            for im in matched:
                left[im] = (f"matched (NCC {placed.pop(im).score:.2f}) but it does not agree with the "
                            f"other observations: residual {worst:.2f} px > {tol_px} px")
    kept = {**observed, **{im: (p.col, p.row) for im, p in placed.items()}}
    if len(kept) >= 2:
        for image in [im for im in targets if im in left]:
            pred = predict_observation(model, images, kept, image)
            if pred is not None and pred.confirmed and pred.score is None:
                placed[image] = pred
                left.pop(image)
    return placed, left, {im: p for im, p in hints.items() if im in left}
