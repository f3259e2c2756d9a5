"""What the views can see of a bend of the structure.

Every image's pushbroom model re-fits to a warped structure as well as it can; a quadratic warp
that leaves no pixel motion once they have is invisible to the views, and no adjustment finds
it. Measured per model in the metric frame H_A gives (`bend_observability`); `bend_seen` says
why nothing beyond the views is needed, `bend_warning` what to tell the user when something is.
The corrections that hold what the views cannot see (recon_core.bend.gcp, recon_core.bend.dem)
read this summary.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from recon_core.bend.drive import BendDrive
from recon_core.bend.pushbroom import warp_observability
from recon_core.geometry.affine import apply_affine_3d

# A warp that moves the images by less than this (px RMS per metre at the site's edge) once
# each image's pushbroom model re-fits is invisible to them (3 views of one date: 1e-5 to 7e-4;
# `demo`'s 6 views of two dates: >= 0.002; `large`'s 9: >= 0.008 for every vertical warp)
BEND_INVISIBLE_PX_PER_M = 1e-3
# ... and worth a warning on sites wider than this: the bend such a warp lets through grows
# with the site (measured with 3 views: 0.4 m over 1.3 km, 1.5-2.9 m over 2.5 km)
BEND_WARN_WIDTH_KM = 1.0

@dataclass(frozen=True)
class BendView:
    """What a model's views can see of a bend of its structure (bend_observability).

    Attributes:
        views: images with enough points.
        site_width_km: the site's width.
        singular_px_per_m: (9,) pixel motion (RMS, px) each quadratic warp, 1 m at the site's
            edge, leaves once every image's pushbroom model re-fits, weakest last.
        vertical_share: (9,) each of those warps' vertical share.
        weakest_vertical_px_per_m: the weakest mostly vertical warp's (None: none).
        invisible_warps: how many move the images by less than BEND_INVISIBLE_PX_PER_M.
        warps: (9, 9) the warps, rows a-major over E, N, U x e^2, e n, n^2, in the metric frame;
        centre_m, half_width_m: e, n = (E, N - centre_m) / half_width_m.
    """

    views: int
    site_width_km: float
    singular_px_per_m: list[float]
    vertical_share: list[float]
    weakest_vertical_px_per_m: float | None
    invisible_warps: int
    warps: list[list[float]]
    centre_m: list[float]
    half_width_m: float

    def with_width(self, site_width_km: float) -> "BendView":
        return replace(self, site_width_km=site_width_km)

    def to_dict(self) -> dict:
        """The record report.json and upgrade/group_<g>.json keep."""
        return {"views": self.views, "site_width_km": self.site_width_km,
                "singular_px_per_m": list(self.singular_px_per_m), "vertical_share": list(self.vertical_share),
                "weakest_vertical_px_per_m": self.weakest_vertical_px_per_m,
                "invisible_warps": self.invisible_warps,
                "basis": {"warps": self.warps, "centre_m": self.centre_m, "half_width_m": self.half_width_m,
                          "meaning": "the warps of singular_px_per_m (rows, a-major over E, N, U x e^2, e n, "
                                     "n^2; e, n = (E, N - centre_m) / half_width_m), in the metric frame"},
                "meaning": "pixel motion (RMS, px) that each quadratic warp of the structure, 1 m at "
                           "the site's edge, leaves once every image's pushbroom model re-fits: a warp "
                           f"below {BEND_INVISIBLE_PX_PER_M:g} px per m is invisible to the images, and 4 "
                           "GCPs (an affine map) do not fix it either"}


def bend_observability(model, H: np.ndarray, max_per_image: int = 20000, seed: int = 0) -> BendView | None:
    """What a model's views can see of a bend of its structure, in the metric frame H_A gives
    (recon_core.bend.pushbroom.warp_observability over its points, each point once per
    image, at most max_per_image per image): BendView; None for a model of fewer than 2 images
    with points."""
    ids = model.point_ids()
    if len(ids) < 100:
        return None
    X = apply_affine_3d(H, model.X[ids])
    slot = np.full(len(model.X), -1, np.int64)
    slot[ids] = np.arange(len(ids))
    o = model.obs
    rng = np.random.default_rng(seed)
    images = []
    for _, k in model.views_per_image(min_points=50):
        if len(k) > max_per_image:
            k = np.sort(rng.choice(k, max_per_image, replace=False))
        images.append((slot[o.track[k]], o.xy[k]))
    if len(images) < 2:
        return None
    w = warp_observability(X, images)
    s = np.asarray(w["singular_px_per_m"])
    vertical = np.linalg.norm(w["warps"][:, 6:], axis=1)
    weakest = s[vertical > 0.5]
    return BendView(views=len(images), site_width_km=2.0 * w["half_width_m"] / 1000.0,
                    singular_px_per_m=s.tolist(), vertical_share=vertical.tolist(),
                    weakest_vertical_px_per_m=float(weakest.min()) if len(weakest) else None,
                    invisible_warps=int(np.sum(s < BEND_INVISIBLE_PX_PER_M)),
                    warps=np.asarray(w["warps"]).tolist(), centre_m=w["centre_m"], half_width_m=w["half_width_m"])


def bend_seen(b: BendView | None) -> str | None:
    """Why the views' bend needs nothing beyond them (they see it, or the site is too small to
    bend), or None when they cannot see a vertical bend of a site of BEND_WARN_WIDTH_KM or more."""
    if b is None:
        return "no two views of the structure to tell a bend"
    if b.site_width_km < BEND_WARN_WIDTH_KM:
        return (f"the site is {b.site_width_km:.2f} km wide, too small to bend (a DEM is used from "
                f"{BEND_WARN_WIDTH_KM:g} km)")
    s = b.weakest_vertical_px_per_m
    if s is None or s >= BEND_INVISIBLE_PX_PER_M:
        return "the views see the bend (several dates, or views from more than one direction)"
    return None


def bend_warning(b: BendView | None, gcp_fit: dict | None = None, drive: BendDrive | None = None) -> str | None:
    """One line when the views cannot see a vertical bend of a site wider than
    BEND_WARN_WIDTH_KM (and the control GCPs did not hold it: gcp_fit, the summary of
    recon_core.bend.gcp); None otherwise. With `drive` (recon_core.bend.drive), it says how
    large a bend the images' own departures from affine suggest."""
    if b is None or bend_seen(b):
        return None
    s = b.weakest_vertical_px_per_m
    text = (f"its {b.views} views cannot see a bend of the structure (a height warp of 1 m over "
            f"its {b.site_width_km:.1f} km moves them by {s:.0e} px): 4 GCPs fix an affine map, not a "
            "bend, so heights away from the GCPs may be off")
    if drive is not None:
        text += (f"; the images' own departures from affine ({drive.departure_px:.1f} px) suggest a bend "
                 f"of about {drive.expected_rms_m:.2g} m RMS, {drive.expected_edge_m:.2g} m at the edges "
                 "(its order of magnitude)")
    else:
        text += " by metres (3 views of one date: 1.5-2.9 m over 2.5 km, 30 m RMS over 10 km)"
    text += "; more views make it smaller, control GCPs spread over the site hold it"
    fit = gcp_fit or {}
    need = fit.get("control_gcps_needed")
    if need and fit.get("control_gcps", 0) < need:
        text += f" ({need} or more control GCPs fit the {fit['invisible_warps']} warps it cannot see)"
    if fit.get("loo_rms_bend_m") is not None:
        text += f"; {fit['reason']}"
    return text
