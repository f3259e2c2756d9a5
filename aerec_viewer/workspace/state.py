"""What the workspace page shows, as JSON: the GCPs, and each GCP's observed and predicted
pixel and residual in every image that sees it, where its surveyed position projects once the
image's group is upgraded, and its error in metres after an upgrade.

Nothing is computed here that the 3D viewer does not compute the same way: the predictions
are results.predict_unobserved (the state table's "predicted"), the surveyed positions'
pixels results.predict_surveyed, the residuals results.residual_vectors (the residual vectors
on the image plane), the errors in metres gcp_panel.upgrade_errors_m (the working-set
table's)."""

from __future__ import annotations

import math
from dataclasses import dataclass

from recon_core.context import UpgradeMaps
from recon_core.io.gcps import GCP

from ..gcp_panel import upgrade_errors_m
from ..results import predict_surveyed, predict_unobserved, residual_vectors
from .tiles import levels


@dataclass(frozen=True)
class Snapshot:
    """The working set as the update thread saw it (a copy: the page's reads never race an edit)."""

    version: int                      # the workspace's state version (WorkspaceApi.version)
    gcps: list[GCP]
    images: dict[str, tuple[int, int]]  # site image -> (width, height), in site order
    registered: set[str]               # images the reconstruction registered
    models: dict                       # group -> SparseModel (replaced whole, never changed)
    outcome: object | None             # the viewer's last upgrade (results.UpgradeOutcome)
    upgrade: UpgradeMaps | None        # the upgrade shown (GcpController.upgrade_maps): its maps
    upgrade_stale: bool                # the GCPs changed since that upgrade
    undo: str | None                   # what Undo / Redo would do
    redo: str | None
    site: str


def _num(v: float, nd: int = 3) -> float | None:
    return round(float(v), nd) if v is not None and math.isfinite(v) else None


def gcp_images(g: GCP, models: dict, images: list[str], upgrade: UpgradeMaps | None = None) -> dict[str, dict]:
    """Image -> {observed, predicted, residual_px, how, source, surveyed} for every image where
    the GCP is observed or predicted. For an observed image the predicted pixel is where its
    point triangulated from all its observations projects (observed - residual); for the
    others, the prediction shown there (results.predict_unobserved): from its observations in
    that image's group (source "observations"), or from its surveyed position once the group is
    upgraded and it has fewer than 2 observations there (source "surveyed"). `surveyed`: where
    its surveyed position projects through the upgrade, in every image of an upgraded group
    (observed - surveyed is its error in the upgrade, in pixels), else None."""
    res = residual_vectors(models, g.observations)
    ground = predict_surveyed(models, images, upgrade, g.llh)
    out: dict[str, dict] = {}
    for im, (c, r) in g.observations.items():
        v = res.get(im)
        out[im] = {"observed": [_num(c), _num(r)],
                   "predicted": None if v is None else [_num(c - v[0]), _num(r - v[1])],
                   "residual_px": None if v is None else _num(math.hypot(*v)),
                   "how": None if v is None else "its point triangulated from its observations",
                   "source": None if v is None else "observations"}
    for im, p in predict_unobserved(models, g.observations, images, upgrade, g.llh).items():
        out[im] = {"observed": None, "predicted": [_num(p.col), _num(p.row)], "residual_px": None,
                   "how": p.how, "source": p.source}
    for im, entry in out.items():
        s = ground.get(im)
        entry["surveyed"] = None if s is None else [_num(s.col), _num(s.row)]
    return out


def gcp_entry(g: GCP, snap: Snapshot, errors: dict) -> dict:
    """One GCP of the list: who it is, where on the ground, its images, its error in metres."""
    err = errors.get(g.id)
    return {"id": g.id, "role": g.role, "enabled": g.enabled,
            "lon": g.lon, "lat": g.lat, "h": g.h, "sigma_h_m": g.sigma_h_m,
            "picked_on_cloud": sorted(g.affine_picked),
            "error_m": None if err is None else {"E": _num(err[0]), "N": _num(err[1]), "U": _num(err[2]),
                                                "left_out": err[3]},
            "images": gcp_images(g, snap.models, list(snap.images), snap.upgrade)}


def workspace_state(snap: Snapshot) -> dict:
    """The whole state the page draws (JSON-ready)."""
    errors = upgrade_errors_m(snap.outcome)
    return {
        "version": snap.version,
        "site": snap.site,
        "images": [{"name": n, "width": w, "height": h, "levels": levels(w, h),
                    "registered": n in snap.registered} for n, (w, h) in snap.images.items()],
        "gcps": [gcp_entry(g, snap, errors) for g in snap.gcps],
        "model": bool(snap.models),
        "upgrade": None if snap.outcome is None else {"stale": snap.upgrade_stale},
        "undo": snap.undo,
        "redo": snap.redo,
    }
