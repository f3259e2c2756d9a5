"""The sparse stage's closing adjustments: the corrections the pushbroom model makes possible on
a grown affine model, each behind one function, and the one order they run in (`closing_plan`,
which recon_core.sparse.sfm follows).

- `check_image_models`: which images the pushbroom family explains; the tie and the within-tile
  correction stand aside for the others.
- `straight_lines`: whether the sensors are straight line arrays, as the bend step needs.
- `image_ties`: each image's tile cameras tied to one pushbroom model (sfm.tie_sigma_px).
- `within_tile`: each image's model's departure from affine inside a tile, taken out of its
  observations (sfm.correction_rounds).
- `bend_step`: the quadratic bend of the structure the images' straight-line models see, taken
  out (sfm.bend_step).

The two checks return typed results (`ImageModelCheck`, `StraightLines`) whose `summary()` is
what the run's report says of them; `image_ties` returns the ties the adjustment takes,
`within_tile` and `bend_step` the summaries the report gives.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from recon_core.bend.image_model import Tie, image_tie
from recon_core.bend.pushbroom import (
    MAX_FOCAL_SHARE,
    MAX_MODEL_MISFIT_PX,
    MAX_STRAIGHT_MISFIT_PX,
    MIN_POINTS_PER_IMAGE,
    MIN_TILES_FOR_CORRECTION,
    estimate_bend,
    model_misfit,
    tile_corrections,
)
from recon_core.model.sparse_model import SparseModel

# the per-image tie's sigma is given for a group of this many images (tie_sigma scales it)
TIE_REFERENCE_VIEWS = 3


@dataclass(frozen=True)
class ClosingStep:
    """One step of the closing adjustments: `filter` (outliers), `bend` (the bend step) or
    `adjust` (a global adjustment with the per-image ties; `correct`: the within-tile correction
    refitted first; `converge`: to bundle.rel_tol)."""

    name: str
    correct: bool = False
    converge: bool = False


def closing_plan(rounds: int, bend: bool) -> tuple[ClosingStep, ...]:
    """The closing adjustments in the order they run. Without correction rounds (one date, or
    sfm.correction_rounds = 0): two converged adjustments, each after an outlier filter. With
    them: one tied adjustment, then per round an outlier filter, the bend step when `bend` (the
    sensors are straight line arrays), an adjustment with the correction refitted (the last one
    converged); then one last bend step, since the last adjustment slides part of the way back
    (its minimum is flat along these warps)."""
    if rounds <= 0:
        return (ClosingStep("filter"), ClosingStep("adjust", converge=True)) * 2
    plan = [ClosingStep("filter"), ClosingStep("adjust")]
    for k in range(1, rounds + 1):
        plan += [ClosingStep("filter")] + ([ClosingStep("bend")] if bend else [])
        plan.append(ClosingStep("adjust", correct=True, converge=k == rounds))
    return tuple(plan + ([ClosingStep("bend")] if bend else []))


@dataclass
class ImageModelCheck:
    """Which images the pushbroom family explains (pushbroom.model_misfit, px of systematic
    error per image); `unexplained`: the indices of those it does not."""

    misfit_px: dict[str, float] = field(default_factory=dict)
    unexplained_names: list[str] = field(default_factory=list)
    unexplained: set[int] = field(default_factory=set)

    def summary(self) -> dict:
        return {"misfit_px": self.misfit_px, "max_misfit_px": MAX_MODEL_MISFIT_PX,
                "unexplained": self.unexplained_names}

    def warning(self) -> str | None:
        """One line when the model misses some images, else None."""
        if not self.unexplained_names:
            return None
        worst = max(self.unexplained_names, key=lambda name: self.misfit_px[name])
        return (f"the pushbroom model does not explain {len(self.unexplained_names)} of {len(self.misfit_px)} "
                f"images ({worst}: {self.misfit_px[worst]:.2f} px > {MAX_MODEL_MISFIT_PX} px, systematic): "
                "the tie and the within-tile correction stand aside for them")


def check_image_models(m: SparseModel) -> ImageModelCheck:
    """Which images the pushbroom family explains, on the grown structure, before any closing
    adjustment: the tie and the within-tile correction stand aside for an image it does not (its
    model's own error would be read as a bend of the structure and put into it)."""
    misfit = {}
    for i, k in m.views_per_image(min_points=MIN_POINTS_PER_IMAGE, min_tiles=MIN_TILES_FOR_CORRECTION):
        misfit[m.images[i]] = round(model_misfit(m.X[m.obs.track[k]], m.obs.xy[k]), 4)
    bad = sorted(name for name, v in misfit.items() if v > MAX_MODEL_MISFIT_PX)
    return ImageModelCheck(misfit, bad, {m.images.index(name) for name in bad})


@dataclass
class StraightLines:
    """Whether the images' sensors are straight line arrays (the bend step runs only then), and
    why not; the per-image misfits of the straight-line model and the focal-plane terms' share."""

    straight: bool
    why: str = ""
    misfit_px: dict[str, float] | None = None
    focal_share: dict[str, float] | None = None

    def summary(self) -> dict:
        out: dict = {"straight": self.straight}
        if self.misfit_px is not None:
            out.update(misfit_px=self.misfit_px, max_misfit_px=MAX_STRAIGHT_MISFIT_PX,
                       focal_share=self.focal_share, max_focal_share=MAX_FOCAL_SHARE)
        if self.why:
            out["why"] = self.why
        return out


def straight_lines(m: SparseModel) -> StraightLines:
    """Are the images' sensors straight line arrays, as the bend step needs? In one image a
    quadratic bend of the structure shows only as the row's c^2, which a bowed line makes too:
    the bend step can only tell them apart where every line is straight. Tried on a copy: the
    bend the straight-line models see taken out, each image's straight-line model must then
    explain it to MAX_STRAIGHT_MISFIT_PX (pushbroom.model_misfit, focal_plane=False), or, where
    it does not, its miss must not be a focal plane's: the focal-plane terms must take away less
    than MAX_FOCAL_SHARE of its power (a miss they mostly do not take away is not a bowed
    line's, whose c^2 the bend step would read as a bend). A sensor with a bowed or distorted
    line fails both (omaha_3dates: 0.04-0.17 px, of which the focal-plane terms take away
    0.55-0.98); this project's straight sensors pass (small sites: under 0.02 px; `large`:
    0.03-0.11 px, of which they take away 0.33-0.60)."""
    pts, images = m.point_views(min_tiles=MIN_TILES_FOR_CORRECTION)
    views = m.views_per_image(min_tiles=MIN_TILES_FOR_CORRECTION)
    if len(images) < 2:
        return StraightLines(False, "fewer than 2 images with 4 registered tiles")
    X = m.X[pts]
    warp, info = estimate_bend(X, images, focal_plane=False)
    if info["warps_seen"]:
        X = X + warp(X)
    mis, share = {}, {}
    for (i, _), (p, xy) in zip(views, images):
        if len(p) < MIN_POINTS_PER_IMAGE:
            continue
        s = model_misfit(X[p], xy, focal_plane=False)
        mis[m.images[i]] = round(s, 4)
        if s > MAX_STRAIGHT_MISFIT_PX:
            f = model_misfit(X[p], xy, focal_plane=True)
            share[m.images[i]] = round(1.0 - min(f / s, 1.0) ** 2, 3)
    bad = sorted((share[k], mis[k], k) for k in share if share[k] > MAX_FOCAL_SHARE)
    why = ""
    if bad:
        sh, px, name = bad[-1]
        why = (f"{name} is not a straight line array ({px:.2f} px of systematic error "
               f"> {MAX_STRAIGHT_MISFIT_PX} px once the bend it sees is out, {sh:.0%} of it "
               f"taken away by the focal-plane terms > {MAX_FOCAL_SHARE:.0%})")
    return StraightLines(not bad, why, mis, share)


def tie_sigma(sigma_px: float, n_views: int) -> float:
    """The per-image tie's sigma for a model of n_views images: sigma_px for a group of 3,
    scaled by 3 / n_views (its weight by (n_views / 3)^2): every view adds conditions on what
    the tie must discriminate (docs: research-notes.md, "The image model and the bend")."""
    return sigma_px * TIE_REFERENCE_VIEWS / max(n_views, TIE_REFERENCE_VIEWS)


def image_ties(m: SparseModel, idx: np.ndarray, sigma_px: float, unexplained: set[int]) -> list[Tie]:
    """One pushbroom tie per image with >= 4 registered tiles whose model explains it
    (recon_core.bend.image_model), over the active observations idx, weighted by
    (sigma_obs / sigma_tie)^2: sigma_obs from the reprojection error, sigma_tie from sigma_px
    (sfm.tie_sigma_px; 0: no tie) and the number of images (tie_sigma)."""
    if sigma_px <= 0:
        return []
    _, err = m.reprojection(idx)
    sigma_obs = max(float(np.sqrt(np.mean(err ** 2))) / np.sqrt(2.0), 0.02)
    n_views = len({m.tiles[t].image for t in np.flatnonzero(m.registered)})
    w = (sigma_obs / tie_sigma(sigma_px, n_views)) ** 2
    rng = np.random.default_rng(0)
    track_of, bounds = m.tracks_by_tile(idx)      # the points of every tile, one sort
    ties = []
    for i, name in enumerate(m.images):
        tids = np.array([t for t in np.flatnonzero(m.registered) if m.tiles[t].image == name], np.int64)
        if len(tids) < 4 or i in unexplained:
            continue
        samples = []
        for t in tids:
            k = track_of[bounds[t]:bounds[t + 1]]
            if len(k) > 48:
                k = rng.choice(k, 48, replace=False)
            samples.append(m.X[k])
        ties.append(image_tie(m.cams[tids], samples, tids, w))
    return ties


def within_tile(m: SparseModel, idx: np.ndarray, unexplained: set[int]) -> dict:
    """Refit each image's model and set the within-tile correction of the active observations
    idx (pushbroom.tile_corrections) in m.obs.corr; the other observations, and those of the
    images their model does not explain, get none. Returns the correction's summary (images,
    RMS and largest correction in px). Only in the closing adjustments, after the tie has held
    the structure once: refitted at every global adjustment of the growing model, the
    correction leaves the warps no view sees free to wander
    (docs: research-notes.md, "The within-tile correction needs several dates")."""
    o = m.obs
    idx = idx[~np.isin(o.img[idx], list(unexplained))]
    corr, info = tile_corrections(m.X[o.track[idx]], o.xy[idx], o.tile[idx], o.img[idx])
    o.correction[:] = 0.0
    o.correction[idx] = corr
    return info


def bend_step(m: SparseModel) -> dict:
    """The bend step: the quadratic warp of the structure that every image's straight-line
    model sees (pushbroom.estimate_bend, focal_plane=False), estimated from every image's
    observations (each point once per image, images with enough tiles to fit their model) and
    taken out: the points move by it and each registered tile camera follows its local linear
    part, so that the cameras still see the points where they did; the gauge is then put back
    (`restore_gauge`). Run only where the sensors are straight line arrays (`straight_lines`).
    Returns the estimate's summary, "applied" whether it moved the model."""
    pts, images = m.point_views(min_tiles=MIN_TILES_FOR_CORRECTION)
    if len(images) < 2:
        return {"images": len(images), "applied": False}
    warp, info = estimate_bend(m.X[pts], images, focal_plane=False)
    info = {"applied": bool(info["warps_seen"] > 0), **info}
    if not info["applied"]:
        return info
    # each registered tile camera follows the warp at its points' centre (a tile without
    # active observations: at the structure's centre)
    reg = np.flatnonzero(m.registered)
    held = m.cams[m.fixed].copy()
    m.cams[reg] = warp.follow(m.cams[reg], m.tile_centres()[reg])
    m.X[pts] += warp(m.X[pts])
    restore_gauge(m, held)
    return info


def restore_gauge(m: SparseModel, held: np.ndarray) -> None:
    """Put the held camera entries (m.fixed: the initial pair's canonical frame) back to their
    values `held` after the bend step moved them, by one 3D affine change of frame of every
    camera and point (the structure's shape is unchanged: only its affine frame). The gauge
    holds whole rows (2 of the first tile, 1 of the second): 12 numbers, one affine map."""
    rows = np.argwhere(m.fixed.all(axis=2))                # (t, row) fully held
    if len(rows) != 3:
        return
    new = m.cams[rows[:, 0], rows[:, 1]]                    # (3, 4)
    old = held.reshape(-1, 4) if held.size == 12 else None
    if old is None:
        return
    R = new[:, :3]
    if abs(np.linalg.det(R)) < 1e-12 * max(np.abs(R).max(), 1e-300) ** 3:
        return
    # x = row . [X, 1]; with X = M X' + t the rows become [row[:3] M, row[:3] t + row[3]]
    M = np.linalg.solve(R, old[:, :3])
    t = np.linalg.solve(R, old[:, 3] - new[:, 3])
    m.cams[:, :, :3], m.cams[:, :, 3] = m.cams[:, :, :3] @ M, m.cams[:, :, :3] @ t + m.cams[:, :, 3]
    pts = m.point_ids()
    m.X[pts] = (m.X[pts] - t) @ np.linalg.inv(M).T
