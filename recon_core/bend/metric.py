"""The metric bend step: the horizontal warp no affine frame lets the views see, removed once
the upgrade gives a metric frame.

Every image's pushbroom model (recon_core.bend.pushbroom) has a 1D perspective across
track, col = ... + (u_c - p_c)(s . X): the column's offset from its centre scales with 1 / range.
In an affine frame s is unknown, so it is free, and with it the two warps of a projective map
of the ground plane, X -> X (1 + a . X), are invisible: each image's free s absorbs them, and
they grow with the site (~1 m RMS at 7.5 km: docs: research-notes.md, "The metric bend step").

After the upgrade the frame is metric, and physics knows s: -v / R, v the image's viewing
direction (its mean camera through H_A) and R the slant range of an orbit at its altitude
(`physical_depth`). With s known, the images see the pair, and this step estimates it
(pushbroom.estimate_bend with `depth` and `pair`):
- only the projective pair of the upgrade's ground plane (east, north): estimated here too,
  the vertical warps take up the error of the assumed altitude, and on a two-view crop of 0.5 km
  the weakly seen horizontal ones took up the images' own departure from the model (a warp of
  1.9 m);
- one common relative change of every depth is estimated with them, so the configured altitude
  is only a start: the data say how far the orbit is (`range_change`). Where it says the
  columns' perspective is far from any orbit's (|change| > MAX_RANGE_CHANGE, a range outside
  0.67-2 times the orbit's: e.g. an image whose
  rows, not columns, run across track), nothing is applied and the report says why;
- nothing is applied either unless the views see both warps of the pair and the range (share
  >= MIN_METRIC_SHARE): without the range the data cannot confirm the physics, and the warps
  would follow the assumed altitude (the horizontal warps with the altitude fixed at 500 or
  900 km, for orbits at 623-683 km: E 0.10 -> 0.16 / 0.14 m instead of 0.03 m on `large`'s
  harness). Small sites do not see all three (`demo`'s 1.1 km: the third at 0.035; the 0.5 km
  pairs: 0.004-0.023); there the pair is small anyway.

The warp is a map of the affine frame (a BendWarp), applied before H_A: the upgrade is then
X -> H_A (X + D(X)) (recon_core.geometry.enu_map.EnuMap). H_A is refitted on the warped structure.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from recon_core.bend.pushbroom import MIN_TILES_FOR_CORRECTION, estimate_bend, physical_depth
from recon_core.bend.result import BendFit
from recon_core.geometry.enu_map import BendWarp

MIN_METRIC_SHARE = 0.1      # a warp is estimated when this share of its pixel motion is seen.
                            # Measured: `large`'s pair and range at 0.28-0.55 (render-free,
                            # 3.6 km) and 0.32-0.63 (pipeline); La Reunion's two views of 0.5 km see one
                            # direction of the pair at 0.02-0.1, and with it the step moved a
                            # check point by 0.5 m (E 0.04 -> 0.29 m): at 0.1 it is left out
MAX_RANGE_CHANGE = 0.5      # the data's depths more than 50 % off the orbit's: not a pushbroom
                            # whose columns run across track at that altitude


def metric_bend(model, H: np.ndarray, altitude_m: float,
                min_share: float = MIN_METRIC_SHARE, pair_only: bool = True) -> BendFit[BendWarp]:
    """The metric bend step of a sparse model with its upgrade H (4, 4) (see the module
    docstring), each image's observations once per point, in images of at least
    MIN_TILES_FOR_CORRECTION tiles. Returns a BendFit: the warp (a BendWarp; None when nothing
    is to be applied) and a summary: the warps' shares, how many were seen, the data's range
    change and the altitude it implies, and the warp's size on the ground (m)."""
    pts, images = model.point_views(min_tiles=MIN_TILES_FOR_CORRECTION)
    out = {"applied": False, "images": len(images), "altitude_km": altitude_m / 1e3}
    if len(images) < 2:
        return BendFit(None, {**out, "reason": f"{len(images)} image(s) with >= {MIN_TILES_FOR_CORRECTION} tiles"})
    X = model.X[pts]
    A3 = H[:3, :3]
    Hinv = np.linalg.inv(H)
    depth = []
    for p, xy in images:
        P = np.linalg.lstsq(np.hstack([X[p], np.ones((len(p), 1))]), xy, rcond=None)[0].T
        depth.append(A3.T @ physical_depth(P @ Hinv, altitude_m))
    east_north = np.linalg.solve(A3, np.eye(3)[:, :2]).T        # affine displacements of 1 m E, N
    warp, info = estimate_bend(X, images, min_share=min_share, depth=depth, range_free=True,
                               directions=east_north, pair=A3[:2] if pair_only else None)
    if info["images"] < 2:
        return BendFit(None, {**out, "images": info["images"],
                              "reason": f"{info['images']} image(s) with enough points for the estimate"})
    k = info["range_change"]
    moved = np.linalg.norm((warp(X) @ A3.T)[:, :2], axis=1)
    out.update(images=info["images"], warps_seen=info["warps_seen"], warp_shares=info["warp_shares"],
               range_change=k, implied_range_factor=1.0 / (1.0 + k) if k > -1 else None,
               warp_rms_m=float(np.sqrt(np.mean(moved ** 2))) if len(moved) else 0.0,
               warp_max_m=float(moved.max()) if len(moved) else 0.0)
    if abs(k) > MAX_RANGE_CHANGE:
        out["reason"] = (f"the images' column perspective is {1 + k:.2f} times what an orbit at "
                         f"{altitude_m / 1e3:g} km gives (are the columns across track?)")
        return BendFit(None, out)
    need = 3 if pair_only else 7                  # the warps and the common range
    if info["warps_seen"] < need:
        # what is not seen is mixed with what is: an unseen range leaves the warps to the
        # assumed altitude, and nothing in the data says the columns' perspective is an orbit's
        out["reason"] = (f"the views see {info['warps_seen']} of the {need} (the {need - 1} warps and "
                         f"the orbit's range) at a share >= {min_share:g}")
        return BendFit(None, out)
    out["applied"] = True
    return BendFit(warp, out)


def warped_model(model, warp: BendWarp):
    """A copy of a sparse model with its points moved by the warp and each registered tile
    camera following its linear part at the tile's points' centre (BendWarp.follow)."""
    m = model
    pts, reg = m.point_ids(), np.flatnonzero(m.registered)
    cams, X = m.cams.copy(), m.X.copy()
    if len(reg):
        cams[reg] = warp.follow(m.cams[reg], m.tile_centres()[reg])
    X[pts] += warp(m.X[pts])
    return replace(m, cams=cams, X=X)
