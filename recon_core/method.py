"""The method as it runs: every step in order, the paper's and those beyond it, in one place.

Each step beyond the paper has the one parameter that switches it off (what `--method paper`
sets: recon_core.config.BEYOND_PAPER is derived from this chain) and says when it stands aside
by itself. The docs page "The method as it runs" is generated from CHAIN, and a test checks it
against the configuration, so the two cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Step:
    name: str
    what: str
    module: str
    paper: bool                      # a step of the paper's method
    switch: str | None = None        # "section.field" that turns a step beyond the paper off
    off: object = None               # ... and its value that does
    stands_aside: str = ""           # when it does nothing by itself


CHAIN: tuple[Step, ...] = (
    Step("group", "images less than 15 days apart form a date group (its span capped)",
         "recon_core.model.grouping", True),
    Step("tile", "each image cut into d x d tiles (d = 1000) overlapping by d/3",
         "recon_core.model.tiling", True),
    Step("features", "SIFT per image, read by window, descriptors kept as uint8",
         "recon_core.sparse.features", True),
    Step("match", "each image matched with its k best partners (an overview match guides it); "
         "the affine fundamental matrix by RANSAC", "recon_core.sparse.matching", True),
    Step("refine", "tie points refined by least-squares patch matching against a view of their "
         "track of the same date (SIFT's positions are off by ~0.35 px)", "recon_core.sparse.refine",
         False, "features.refine_half_px", 0, "a point whose patches correlate below "
         "features.refine_min_ncc keeps its SIFT position"),
    Step("joint", "all date groups in one affine frame, each keeping its own tiles and points",
         "recon_core.sparse.stage", False, "sfm.joint_groups", False,
         "the groups' images do not match across dates: one reconstruction per group"),
    Step("sfm", "incremental affine SfM: the initial image pair with the sparsest matching that "
         "shows parallax, its tile pair with the most matches; Tomasi-Kanade; tiles added one at "
         "a time by RANSAC resection of an 8-parameter affine camera; linear multi-view "
         "triangulation; robust bundle adjustment", "recon_core.sparse.sfm", True),
    Step("image_models", "each image's pushbroom model (focal plane included) checked against "
         "the image: the tie and the within-tile correction stand aside for an image it does not "
         "explain",
         "recon_core.bend.closing", False),
    Step("tie", "each image's tile cameras tied to one pushbroom model in the closing "
         "adjustments", "recon_core.bend.image_model", False, "sfm.tie_sigma_px", 0.0,
         "an image with fewer than 4 registered tiles, or one its model does not explain"),
    Step("bend_step", "the quadratic bend of the structure that the images' straight-line models "
         "see taken out at the start of each correction round, before its adjustment, and once "
         "after the last (several dates only)", "recon_core.bend.closing", False,
         "sfm.bend_step", False, "any sensor that is not a straight line array (checked on the run's "
         "data: its straight-line model misses it by more than 0.02 px, mostly by what the focal-"
         "plane terms take away; a bowed line looks like a bend; every real sensor so far); one date"),
    Step("within_tile", "each image's model's departure from affine inside a tile taken out of "
         "its observations (several dates only)", "recon_core.bend.closing", False,
         "sfm.correction_rounds", 0, "one date (one pass's views cannot see what it would free); "
         "an image its model does not explain"),
    Step("dense", "per overlapping tile pair: affine F from the cameras, rectifying affine maps, "
         "MGM (semi-global matching on a census cost; dense.matcher) with a left-right check, "
         "multi-view tracks with a photometric check, triangulation", "recon_core.dense", True),
    Step("upgrade", "one 4 x 4 affine map H_A fitted on >= 4 control GCPs in a local ENU frame "
         "(least squares, RANSAC when many)", "recon_core.euclidean.upgrade", True),
    Step("view_hold", "each image's line of sight (its tile cameras' null vector) held to its "
         "viewing direction from the metadata in the fit of H_A, the GCPs weighted by their "
         "triangulation covariances: what flat GCPs leave loose (the height scale, the lean of "
         "heights) is fixed by the images, 3 control GCPs suffice", "recon_core.euclidean.held",
         False, "upgrade.view_sigma_deg", 0.0, "fewer than 2 images with a viewing direction in "
         "their sidecar (\"view\"); an image that disagrees with the others by over 1 degree is "
         "left out"),
    Step("metric_prior", "the cameras' metric constraint (the rows of each tile camera "
         "orthogonal in metres) weighed into the fit of H_A", "recon_core.euclidean.metric_prior",
         False, "upgrade.metric_prior_sigma_cos", 0.0),
    Step("metric_bend", "the horizontal warp no affine frame shows, found once H_A gives metres "
         "from each image's 1D perspective", "recon_core.bend.metric", False,
         "upgrade.metric_bend", False, "the views do not see the warps (most sites)"),
    Step("gcp_bend", "the bend the views cannot see fitted to the control GCPs",
         "recon_core.bend.gcp", False, "upgrade.gcp_bend", False,
         "fewer than 9 control GCPs, or it does not predict each one left out better"),
    Step("dem_bend", "the vertical bend taken from a coarse reference DEM",
         "recon_core.bend.dem", False, "upgrade.reference_dem", "",
         "no DEM given, a site under 1 km, views that see the bend, or a DEM too noisy"),
    Step("fusion", "date groups reconstructed apart aligned by ICP; the groups' DSMs fused by "
         "their acquisition geometry", "recon_core.euclidean.dsm_stage", True),
    Step("dsm", "a DSM on a geographic grid (ellipsoidal heights), the cloud as PLY and LAZ",
         "recon_core.euclidean.dsm", True),
    Step("eval", "the DSM against the site's ground truth (median error, completeness within "
         "1 m, error maps) and against other tools' DSMs (agreement)", "recon_core.evaluation", True),
)


def beyond_paper() -> dict:
    """'section.field' -> the value that switches each step beyond the paper off."""
    return {s.switch: s.off for s in CHAIN if not s.paper and s.switch}
