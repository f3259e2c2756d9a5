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
from recon_core.euclidean.metric_prior import camera_rows
from recon_core.euclidean.upgrade import GcpInput, UpgradeResult, upgrade
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
    return GcpAffine("", X[0], len(imgs), float(np.sqrt(np.mean(err ** 2))), "triangulated")


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


def frame_for(gcps: list[GCP]) -> LocalFrame:
    """Local ENU frame at the centroid of the control GCPs (all GCPs if none is control)."""
    sel = [g for g in gcps if g.role == "control" and g.enabled] or [g for g in gcps if g.enabled] or gcps
    if not sel:
        raise ReconstructionError("no GCP: the Euclidean upgrade needs >= 4 control GCPs")
    llh = np.array([g.llh for g in sel])
    return LocalFrame(float(llh[:, 0].mean()), float(llh[:, 1].mean()), float(llh[:, 2].mean()))


def upgrade_group(model: SparseModel, gcps: list[GCP], frame: LocalFrame | None = None, *,
                  ransac_thresh_m: float = 2.0, seed: int = 0,
                  sigma_cos: float = 0.0) -> tuple[UpgradeResult, LocalFrame, dict[str, GcpAffine]]:
    """Fit H_A for one group: affine frame -> local ENU metres (with sigma_cos > 0, with the
    metric constraint of the model's tile cameras: recon_core.euclidean.metric_prior)."""
    frame = frame or frame_for(gcps)
    aff = gcp_affine_points(model, gcps)
    enu = frame.geodetic_to_enu(np.array([g.llh for g in gcps])) if gcps else np.zeros((0, 3))
    inputs = [GcpInput(g.id, g.role, aff[g.id].xyz, enu[k], g.sigma_m, aff[g.id].reproj_rms_px,
                       enabled=g.enabled)
              for k, g in enumerate(gcps)]
    result = upgrade(inputs, ransac_thresh_m=ransac_thresh_m, rng=np.random.default_rng(seed),
                     camera_rows=camera_rows(model) if sigma_cos > 0 else None, sigma_cos=sigma_cos)
    return result, frame, aff


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
