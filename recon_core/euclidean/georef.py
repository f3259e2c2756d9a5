"""From a group's affine model and GCPs to Euclidean coordinates.

1. Each GCP's affine point: its image observations are triangulated with the registered tile
   cameras whose tiles contain them (>= 2 images), or a 3D point picked on the affine cloud.
2. H_A is fitted in a local ENU frame at the control GCPs' centroid (`upgrade.upgrade`).
3. ENU points are converted to geodetic and then to the output CRS (UTM unless site.json says
   otherwise); heights are ellipsoidal h, not ENU up (which drifts by d^2 / 2R).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from recon_core.errors import ReconstructionError
from recon_core.euclidean.control import unusable_reason
from recon_core.euclidean.metric_prior import camera_rows
from recon_core.euclidean.held import SIGMA_VIEW_DEG
from recon_core.euclidean.sight import lines_of_sight
from recon_core.euclidean.upgrade import GcpInput, ImageHold, UpgradeResult, upgrade
from recon_core.geometry import affine
from recon_core.geometry.geodesy import LocalFrame, geodetic_to_projected, utm_epsg_for
from recon_core.io.gcps import GCP
from recon_core.model.sparse_model import SparseModel


@dataclass
class GcpAffine:
    """A GCP's position in a group's affine frame, with how it was obtained."""

    id: str
    xyz: np.ndarray | None        # (3,) or None when it could not be placed
    n_images: int
    reproj_rms_px: float | None
    source: str                   # "triangulated", "picked" or the reason it is missing
    information: np.ndarray | None = None   # (3, 3) sum of M^T M over its observations (px^-2)
    residual_ss: float = 0.0      # their squared reprojection residuals (px^2), one click per image

    @property
    def residual_dof(self) -> int:
        """Degrees of freedom of its reprojection residuals: 2 per image less the 3 of the point."""
        return max(0, 2 * self.n_images - 3) if self.information is not None else 0


def triangulate_gcp(model: SparseModel, observations: dict[str, tuple[float, float]]) -> GcpAffine:
    """Triangulate one GCP from its observations in the images of the model's group."""
    cam_idx, xy, imgs = [], [], set()
    for name, (c, r) in observations.items():
        if name not in model.images:
            continue
        for t in model.tiles_at(name, (c, r)):
            cam_idx.append(t)
            xy.append((c, r))
            imgs.add(name)
    if len(imgs) < 2:
        why = (f"observed in {len(imgs)} registered image(s) of group {model.group}; "
               "needs >= 2 (or pick it on the cloud)")
        return GcpAffine("", None, len(imgs), None, why)
    cam_idx = np.array(cam_idx)
    xy = np.array(xy, dtype=np.float64)
    # seen by each tile camera as its tie points are (the SfM's within-tile correction)
    xy = xy - np.concatenate([model.correction_at(t, p) for t, p in zip(cam_idx, xy)])
    X, ok = affine.triangulate_tracks(model.cams, cam_idx, np.zeros(len(cam_idx), int), xy, 1)
    if not ok[0]:
        return GcpAffine("", None, len(imgs), None, "ill-conditioned triangulation")
    err = affine.reprojection_errors(model.cams, cam_idx, np.zeros(len(cam_idx), int), xy, X)
    # what the observations know of the point: one click per image (tiles of one image that
    # overlap see the same click: each counts for its share)
    share = {name: 1.0 / sum(1 for t in cam_idx if model.tiles[t].image == name) for name in imgs}
    info = np.zeros((3, 3))
    for t in cam_idx:
        M = np.asarray(model.cams[t], np.float64)[:, :3]
        info += share[model.tiles[t].image] * (M.T @ M)
    ss = float(sum(share[model.tiles[t].image] * e ** 2 for t, e in zip(cam_idx, err)))
    return GcpAffine("", X[0], len(imgs), float(np.sqrt(np.mean(err ** 2))), "triangulated",
                     information=info, residual_ss=ss)


def gcp_affine_points(model: SparseModel, gcps: list[GCP]) -> dict[str, GcpAffine]:
    """Affine positions of all GCPs for one group; a position picked on this group's cloud
    (GCP.affine_picked) wins over triangulating the observations."""
    out = {}
    for g in gcps:
        if model.group in g.affine_picked:
            out[g.id] = GcpAffine(g.id, np.asarray(g.affine_picked[model.group], float), 0, None, "picked")
            continue
        a = triangulate_gcp(model, g.observations)
        a.id = g.id
        out[g.id] = a
    return out


def usable_control(model: SparseModel, gcps: list[GCP]) -> dict[str, str | None]:
    """Control GCP id -> None when the upgrade of the model's group can use it, else why not
    (the triangulation the upgrade does: gcp_affine_points; the rule: recon_core.euclidean.control)."""
    ctrl = [g for g in gcps if g.role == "control"]
    aff = gcp_affine_points(model, ctrl)
    out = {}
    for g in ctrl:
        a = aff[g.id]
        why = unusable_reason(g.role, g.enabled, a.xyz, g.llh)
        if why is not None and a.xyz is None and a.source:
            why = a.source                           # the triangulation's own words
        out[g.id] = why
    return out


def frame_for(gcps: list[GCP]) -> LocalFrame:
    """Local ENU frame at the centroid of the control GCPs (all GCPs if none is control)."""
    sel = [g for g in gcps if g.role == "control" and g.enabled] or [g for g in gcps if g.enabled] or gcps
    if not sel:
        raise ReconstructionError("no GCP: the Euclidean upgrade needs >= 4 control GCPs")
    llh = np.array([g.llh for g in sel])
    return LocalFrame(float(llh[:, 0].mean()), float(llh[:, 1].mean()), float(llh[:, 2].mean()))


# The GCPs' pixel noise, pooled over the control GCPs' reprojection residuals:
PIXEL_SIGMA_FLOOR = 0.1       # px: never below it (a click is not better than that)
PIXEL_SIGMA_DEFAULT = 0.3     # px: with too few residuals, a careful click (the shared sites' GCPs)
PIXEL_SIGMA_MIN_DOF = 4       # residual degrees of freedom needed to pool the noise from them
SITE_SAMPLE = 5000            # sparse points that tell how far the site reaches (the tilt's lever)


def pixel_sigma(aff: dict[str, GcpAffine], ids: list[str]) -> float:
    """The pixel noise of the GCPs' observations from their own reprojection residuals."""
    dof = sum(aff[i].residual_dof for i in ids if i in aff)
    ss = sum(aff[i].residual_ss for i in ids if i in aff and aff[i].residual_dof)
    if dof < PIXEL_SIGMA_MIN_DOF:
        return PIXEL_SIGMA_DEFAULT
    return max(PIXEL_SIGMA_FLOOR, float(np.sqrt(ss / dof)))


def upgrade_group(model: SparseModel, gcps: list[GCP], frame: LocalFrame | None = None, *,
                  ransac_thresh_m: float = 2.0, seed: int = 0, sigma_cos: float = 0.0,
                  images: dict | None = None,
                  sigma_view_deg: float = SIGMA_VIEW_DEG) -> tuple[UpgradeResult, LocalFrame, dict[str, GcpAffine]]:
    """Fit H_A for one group: affine frame -> local ENU metres. With `images` (name ->
    ImageInfo) whose metadata states their viewing direction, held by the images' lines of sight
    (recon_core.euclidean.held; sigma_view_deg > 0); with sigma_cos > 0 (and no lines of sight),
    with the metric constraint of the model's tile cameras (recon_core.euclidean.metric_prior)."""
    frame = frame or frame_for(gcps)
    aff = gcp_affine_points(model, gcps)
    enu = frame.geodetic_to_enu(np.array([g.llh for g in gcps])) if gcps else np.zeros((0, 3))
    sig_px = pixel_sigma(aff, [g.id for g in gcps if g.role == "control" and g.enabled])
    inputs = [GcpInput(g.id, g.role, aff[g.id].xyz, enu[k], g.sigma_m, aff[g.id].reproj_rms_px,
                       enabled=g.enabled, affine_cov=_affine_cov(aff[g.id], sig_px), sigma_h_m=g.sigma_h_m)
              for k, g in enumerate(gcps)]
    rays = lines_of_sight(model, images) if images and sigma_view_deg > 0 else []
    ids = model.point_ids()
    if len(ids) > SITE_SAMPLE:
        ids = ids[np.linspace(0, len(ids) - 1, SITE_SAMPLE).astype(int)]
    result = upgrade(inputs, ransac_thresh_m=ransac_thresh_m, rng=np.random.default_rng(seed),
                     camera_rows=camera_rows(model) if sigma_cos > 0 else None, sigma_cos=sigma_cos,
                     hold=ImageHold(rays, frame, sigma_view_deg) if len(rays) >= 2 else None,
                     site_points=model.X[ids])
    return result, frame, aff


def _affine_cov(a: GcpAffine, sigma_px: float) -> np.ndarray | None:
    """The covariance of a GCP's affine point from its observations (None: picked or unplaced)."""
    if a.xyz is None or a.information is None:
        return None
    try:
        return np.linalg.inv(a.information) * sigma_px ** 2
    except np.linalg.LinAlgError:
        return None


def output_epsg(hints: dict, frame: LocalFrame) -> int:
    """The output CRS: site.json's crs_epsg, else the UTM zone of the frame origin."""
    if hints.get("crs_epsg"):
        return int(hints["crs_epsg"])
    lon, lat = frame.origin_llh[:2]
    return utm_epsg_for(float(lon), float(lat))


def enu_to_output(enu: np.ndarray, frame: LocalFrame, epsg: int, chunk: int = 2_000_000) -> np.ndarray:
    """(n, 3) ENU -> (n, 3) (x, y, ellipsoidal h) in the projected CRS `epsg`, by chunks."""
    out = np.empty_like(np.asarray(enu, dtype=np.float64))
    for s in range(0, len(enu), chunk):
        llh = frame.enu_to_geodetic(enu[s:s + chunk])
        out[s:s + chunk] = geodetic_to_projected(llh, epsg)
    return out
