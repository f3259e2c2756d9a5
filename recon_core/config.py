"""All parameters of a run, one dataclass per stage, each field commented.

Named presets (`PRESETS`) tune them for test-size and production-size inputs.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any


# -- the schema: every field's type (its annotation) and its rule, checked in one pass ---------
@dataclass(frozen=True)
class Rule:
    """What a field's value may be, besides its type: a range (numbers, each element of a
    tuple; finite always), a choice among names (the modules that implement them hold the same
    names: tests/test_config_schema.py), odd."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    choices: tuple | None = None
    odd: bool = False

    def problem(self, v: Any) -> str | None:
        """Why v breaks the rule (None: it does not)."""
        if v is None or isinstance(v, bool):
            return None
        if self.choices is not None:
            names = _choices(self.choices)
            return None if v in names else "choose one of " + ", ".join(map(str, names))
        for x in (v if isinstance(v, (tuple, list)) else (v,)):
            if isinstance(x, str):
                continue
            try:
                finite = math.isfinite(x)
            except OverflowError:           # an integer no float holds
                finite = False
            if not finite:
                return "must be a finite number"
            if self.lo is not None and (x < self.lo or (self.lo_open and x == self.lo)):
                return f"must be {'>' if self.lo_open else '>='} {self.lo:g}" + (
                    f" and {'<' if self.hi_open else '<='} {self.hi:g}" if self.hi is not None else "")
            if self.hi is not None and (x > self.hi or (self.hi_open and x == self.hi)):
                return f"must be {'<' if self.hi_open else '<='} {self.hi:g}"
            if self.odd and int(x) % 2 == 0:
                return "must be odd"
        return None


def _choices(key) -> tuple:
    return tuple(key)


def _p(default, **rule):
    """A parameter: its default and its Rule (the schema lives beside each field)."""
    return field(default=default, metadata={"rule": Rule(**rule)})


@dataclass
class GroupingConfig:
    max_gap_days: float = _p(15.0, lo=0, lo_open=True, hi=3660)  # images closer in time than this share a date group
    max_span_days: float | None = _p(30.0, lo=0, lo_open=True, hi=36600)  # cap on a chained group's total span (None = no cap)


@dataclass
class TilingConfig:
    tile_size: int = _p(1000, lo=64, hi=20000)  # d: tile side in pixels (pushbroom ~ affine on a tile)
    overlap: int | None = _p(None, lo=0)  # overlap between neighbouring tiles; None = d // 3


@dataclass
class FeatureConfig:
    max_features_per_mpx: int = _p(30000, lo=100, hi=1_000_000)  # SIFT keypoints kept per megapixel (strongest first)
    contrast_threshold: float = _p(0.01, lo=0, lo_open=True, hi=1)  # SIFT contrast threshold on the 8-bit detection image
    detect_block: int = _p(2048, lo=256, hi=65536)  # images are read by window of this many pixels
    stretch_percentiles: tuple[float, float] = _p((0.5, 99.5), lo=0, hi=100)  # uint16 -> 8-bit robust stretch
    refine_half_px: int = _p(7, lo=0, hi=32)  # tie points refined by least-squares patch matching on
                                      # (2 h + 1)^2 px patches against a view of their track
                                      # of the same date
                                      # (SIFT's own positions are off by ~0.35 px); 0 = off
    refine_min_ncc: float = _p(0.7, lo=-1, hi=1)  # a refined position needs this patch correlation


@dataclass
class MatchingConfig:
    ratio: float = _p(0.8, lo=0, lo_open=True, hi=1)  # Lowe's ratio test
    mutual: bool = _p(True)           # keep only mutual nearest neighbours
    fa_thresh_px: float = _p(1.5, lo=0, lo_open=True, hi=100)  # RANSAC threshold of the affine fundamental matrix (px)
    fa_ransac_iters: int = _p(500, lo=1, hi=1_000_000)  # cap on its RANSAC samples (adaptive below it)
    min_inliers: int = _p(30, lo=4, hi=1_000_000)  # a tile pair with fewer verified matches is dropped
    coarse_factor: int = _p(8, lo=1, hi=64)  # downsampling of the whole-image overview match
    k_partners: int = _p(6, lo=1, hi=1000)  # match each image with its k best partners only


@dataclass
class SfmConfig:
    resect_thresh_px: float = _p(2.0, lo=0, lo_open=True, hi=100)  # RANSAC threshold for tile resection
    resect_ransac_iters: int = _p(500, lo=1, hi=1_000_000)  # cap on its RANSAC samples (adaptive below it)
    image_camera_thresh_factor: float = _p(4.0, lo=1, hi=100)  # one camera fitted to a whole image (the prior of a
                                      # flat tile) departs from the pushbroom by a few pixels:
                                      # its RANSAC threshold is this many times resect_thresh_px
    resect_min_inliers: int = _p(12, lo=4, hi=100_000)  # a tile needs this many 2D-3D inliers to register
    max_reproj_px: float = _p(2.0, lo=0, lo_open=True, hi=100)  # triangulated points with a larger error are dropped
    min_points_conditioning: float = _p(0.01, lo=0, hi=1)  # resection points flatter than this are regularised
    min_triangulation_ratio: float = _p(0.3, lo=0, hi=1)  # drop points whose conditioning (~ B/H of their views) is below
                                      # this fraction of the model's 90th percentile (0 = off)
    init_min_parallax: float = _p(3.0, lo=0, hi=1e6)  # sigma3/sigma4 of an initial tile pair's matches below
                                      # this: no usable parallax (the measurement matrix is near rank 2)
    init_min_inliers: int = _p(60, lo=4, hi=1_000_000)  # the initial tile pair needs at least this many verified matches
    global_ba_growth: float = _p(0.15, lo=0, lo_open=True, hi=100)  # run a global BA when tiles grew by this fraction
    local_ba_window: int = _p(6, lo=1, hi=1000)  # cameras refined in a local BA after each registration
    joint_groups: bool = _p(True)     # reconstruct all date groups in one affine frame when their
                                      # images match across dates (each group keeps its tiles and
                                      # points): all views hold the structure against bending;
                                      # falls back to one reconstruction per group otherwise
    joint_min_matches: int = _p(200, lo=1, hi=10_000_000)  # verified matches an image needs with the other groups'
                                      # images for the joint reconstruction
    joint_partners: int = _p(2, lo=1, hi=1000)  # images of other groups each image is matched with
    tie_sigma_px: float = _p(0.0, lo=0, hi=100)  # the per-image pushbroom tie (recon_core.bend.image_model)
                                      # in the final global adjustments: the model's error against
                                      # a pushbroom, px, for a model of 3 images; n > 3 images
                                      # scale it by 3 / n (0 = off, the default: with the focal
                                      # plane in the model it holds no bend and changed no
                                      # reference's DSM; docs: accuracy.md)
    correction_rounds: int = _p(1, lo=0, hi=20)  # closing global adjustments after the first tied one, each
                                      # with the within-tile correction refitted (each image's
                                      # pushbroom model's departure from affine inside a tile
                                      # taken out of its observations: what drives the bend;
                                      # recon_core.bend.pushbroom), in a joint reconstruction
                                      # of several dates (one pass's views cannot see the vertical
                                      # warps it would free) (0 = none; each round more lowers
                                      # the bend further and costs one global adjustment)
    bend_step: bool = _p(True)        # each correction round starts by taking out the quadratic warp
                                      # of the structure the images' straight-line models see, and
                                      # the last adjustment is followed by one; only where every
                                      # sensor is a straight line array (checked on the run's data:
                                      # a bowed line looks like a bend; docs: accuracy.md)


@dataclass
class BundleConfig:
    loss: str = _p("huber", choices=("linear", "huber", "cauchy"))  # robust loss of scipy.optimize.least_squares
    loss_scale_px: float = _p(1.0, lo=0, lo_open=True, hi=1000)  # f_scale of the robust loss, pixels
    max_nfev: int = _p(50, lo=1, hi=100_000)  # LM iteration cap of a global adjustment
    local_max_nfev: int = _p(10, lo=1, hi=100_000)  # LM iteration cap of a local adjustment (after each tile)
    rel_tol: float = _p(1e-6, lo=0, lo_open=True, hi=1, hi_open=True)  # an adjustment stops when an iteration lowers the robust
                                      # cost by less than this fraction of it ...
    growing_rel_tol: float = _p(1e-5, lo=0, lo_open=True, hi=1, hi_open=True)  # ... and this one while the model grows (local and
                                      # intermediate global adjustments): the final global
                                      # adjustments converge to rel_tol from there
    solver: str = _p("auto", choices=("auto", "dense", "sparse"))  # reduced camera system: dense (Cholesky), sparse (8 x 8
                                      # blocks, SuperLU: 10-20 km sites) or auto (sparse from
                                      # 1,500 camera unknowns)


@dataclass
class DenseConfig:
    step: int = _p(1, lo=1, hi=64)    # stride of the reference-pixel grid (1 = every pixel)
    matcher: str = _p("mgm", choices=("sgbm", "mgm", "pandora"))  # stereo matcher (recon_core.dense.matchers.MATCHERS);
                                      # its parameters are the config section of the same name:
                                      # "mgm" the paper's (census + MGM, built in); "sgbm" OpenCV's
                                      # (faster, sharper walls on this project's simulator, less
                                      # accurate on real and independent scenes); "pandora"
                                      # (CNES's census + SGM) needs the optional extra:
                                      # pip install 'aerec[pandora]' (docs: accuracy.md, "Matchers: SGBM, MGM and pandora")
    disp_margin_px: float = _p(8.0, lo=0, hi=10_000)  # margin added around the sparse disparity percentiles
    disp_margin_frac: float = _p(0.25, lo=0, hi=100)  # ... plus this fraction of the percentile range
    min_pair_matches: int = _p(20, lo=4, hi=1_000_000)  # a tile pair needs this many sparse matches to be matched
    min_parallax_ratio: float = _p(3.0, lo=0, hi=1e6)  # sigma3/sigma4 of the pair's sparse matches (baseline test)
    max_two_view_spread: float = _p(2.0, lo=0, hi=1e6)  # a two-view point whose pair triangulates more than this
                                      # many times less precisely than the group's best pair is
                                      # marked weak: a DSM cell uses it only when no other point
                                      # falls there (0 = mark none)
    core_margin_px: int = _p(48, lo=0, hi=10_000)  # context matched around the part of a tile it owns (px)
    ncc_radius: int = _p(2, lo=1, hi=15)  # photometric check patch radius (5 x 5 patches)
    min_ncc: float = _p(0.3, lo=-1, hi=1)  # links with a lower NCC are dropped
    max_reproj_px: float = _p(1.0, lo=0, lo_open=True, hi=100)  # views with a larger error are dropped from a track
    view_drop_rounds: int = _p(3, lo=0, hi=100)  # rounds of dropping a track's worst view and re-triangulating
    workers: int | None = _p(None, lo=1, hi=1024)  # local worker processes (None = all cores, 1 = serial)
    scheduler: str | None = _p(None)  # dask.distributed scheduler address (None = local pool)


@dataclass
class SgbmConfig:
    """OpenCV StereoSGBM (3-way) with a true left-right check (a second run on the mirrored pair)."""

    block_size: int = _p(5, lo=1, hi=31, odd=True)  # matching block (odd)
    p1: int = _p(8, lo=0, hi=10_000)  # smoothness penalty P1, times block_size^2
    p2: int = _p(32, lo=0, hi=100_000)  # smoothness penalty P2, times block_size^2
    uniqueness: int = _p(10, lo=0, hi=100)  # uniqueness ratio (%)
    speckle_window: int = _p(100, lo=0, hi=100_000)  # speckle filter: max region size (px) to remove
    speckle_range: int = _p(2, lo=0, hi=1000)  # speckle filter: max disparity variation (px)
    lr_max_diff_px: float = _p(1.0, lo=0, hi=1000)  # left-right consistency tolerance (px)


@dataclass
class MgmConfig:
    """MGM (More Global Matching, Facciolo et al. 2015: the paper's matcher, and s2p's) on a census
    cost, built in (recon_core.dense.mgm): 8 directions, each message from two neighbours,
    winner-take-all, V-fit sub-pixel refinement, a left-right check, a 3 x 3 median, a speckle
    filter."""

    census_window: int = _p(5, choices=(3, 5, 7))  # census window side (px); costs run from 0 to census_window^2 - 1
    p1: float = _p(12.0, lo=0, hi=10_000)  # penalty of a 1 px disparity step (census units; 12 rather
                                      # than CARS's 8: closer to the truth on omaha and to s2p on
                                      # both real pairs; docs: research-notes.md, "MGM's penalties")
    p2: float = _p(32.0, lo=0, hi=100_000)  # penalty of a larger step (>= p1)
    lr_max_diff_px: float = _p(1.0, lo=0, hi=1000)  # left-right check tolerance (px)
    median: bool = _p(True)           # 3 x 3 median of the valid disparities
    uniqueness: float = _p(0.1, lo=0, hi=10)  # a winner whose cost another disparity (> 1 px away) comes within
                                      # this fraction of is ambiguous: dropped (0 = keep all)
    speckle_window: int = _p(100, lo=0, hi=100_000)  # speckle filter: max region size (px) to remove (0 = none)
    speckle_range: float = _p(2.0, lo=0, hi=1000)  # speckle filter: max disparity step inside a region (px)
    max_volume_mb: float = _p(512.0, lo=16, hi=1_000_000)  # a worker's 3 cost volumes together stay under
                                      # this (MB): larger canvases are matched in row strips
                                      # overlapping by 64 rows


@dataclass
class PandoraConfig:
    """CNES's pandora with pandora_plugin_libsgm, set up as CNES CARS matches satellite pairs:
    census cost, SGM over 8 directions, winner-take-all, V-fit sub-pixel refinement, a median
    filter and accurate cross-checking (a second run from the right image). An optional extra:
    pip install 'aerec[pandora]'."""

    census_window: int = _p(5, choices=(3, 5, 7, 9, 11, 13))  # census window side (px; CARS: 5, its urban profile 11)
    p1: float = _p(8.0, lo=0, lo_open=True, hi=10_000)  # SGM penalty of a 1 px disparity step (CARS: 8)
                                      # (census costs run from 0 to census_window^2)
    p2: float = _p(32.0, lo=0, lo_open=True, hi=100_000)  # SGM penalty of a larger step (> p1; CARS: 32)
    refinement: str = _p("vfit", choices=("vfit", "quadratic"))  # sub-pixel refinement of the winning disparity
    median_size: int = _p(3, lo=1, hi=15, odd=True)  # median filter of the disparity map (px; 1 = none)
    lr_max_diff_px: float = _p(1.0, lo=0, hi=1000)  # cross-checking tolerance (px)


@dataclass
class UpgradeConfig:
    ransac_thresh_m: float = _p(2.0, lo=0, lo_open=True, hi=10_000)  # GCP inlier threshold of the H_A RANSAC (metres)
    allow_flat_gcps: bool = _p(False)  # go on when the control GCPs and the images cannot fix the
                                      # height scale: expected height error > 10 m on a 40 m structure
    view_sigma_deg: float = _p(0.1, lo=0, hi=10)  # the images' lines of sight hold the fit of H_A where the
                                      # metadata states their viewing direction ("view" in each
                                      # image's sidecar): the prior sigma of one (degrees; estimated
                                      # from the fit's residuals when the images are redundant);
                                      # 0 = the GCPs alone (recon_core.euclidean.held)
    metric_prior_sigma_cos: float = _p(0.0, lo=0, hi=1)  # the cameras' metric constraint in the fit of H_A: the
                                      # cosine between a tile camera's rows in metres, per image
                                      # (recon_core.euclidean.metric_prior; 0 = GCPs only, the
                                      # default: it moved every independent reference's check
                                      # points horizontally; 2e-3 for groups reconstructed apart)
    metric_bend: bool = _p(True)      # the metric bend step (recon_core.bend.metric): the
                                      # horizontal warp no affine frame lets the views see, found once
                                      # H_A gives metres, each image's 1D perspective from its orbit
    gcp_bend: bool = _p(True)         # fit the bend the views cannot see to >= 9 control GCPs
                                      # (recon_core.bend.gcp): kept only when it
                                      # predicts each control GCP left out better than H_A alone
    orbit_altitude_km: float = _p(694.0, lo=100, hi=50_000)  # its start: the orbit's altitude (Pleiades, SPOT 6/7: 694;
                                      # Pleiades Neo, WorldView-3: ~620); the step then estimates one
                                      # common change of the ranges from the data (10 % off: harmless)
    reference_dem: str = _p("")       # a coarse DEM of the site (GeoTIFF: SRTM, Copernicus GLO-30, a
                                      # national DEM; any CRS, geoid or ellipsoid heights) that holds
                                      # the vertical bend the views cannot see when the GCPs do not
                                      # (recon_core.bend.dem); "" = none
    reference_dem_degree: int = _p(2, choices=(2, 3))  # the degree of the vertical bend taken from it: 2 (a dome or a
                                      # saddle) or 3, only for a DEM whose errors do not reach over
                                      # km (Copernicus GLO-30 class; with errors correlated over 1 km,
                                      # SRTM class, 3 does worse;
                                      # docs: research-notes.md, "The vertical bend from a reference DEM")


@dataclass
class DsmConfig:
    resolution_m: float | None = _p(None, lo=0.01, hi=1000)  # output cell size; None = site.json's, else the GSD
    stat: str = _p("median", choices=("median", "upper_median", "max", "min", "mean"))  # per-cell statistic: median | upper_median | max | min | mean
    fill_holes_px: int = _p(2, lo=0, hi=1000)  # fill only holes this small (radius, cells) with support
    laz: bool = _p(True)              # also write cloud.laz (LAS 1.4 with the CRS) from cloud.ply
    fusion_correction_m: float = _p(32.0, lo=0, hi=1e6)  # a lower-ranked group is brought onto the fused surface by
                                      # a smooth correction (medians of the difference in blocks
                                      # of this size) before it fills holes; 0 = off
    fusion_agree_sigmas: float = _p(2.5, lo=0, hi=1000)  # cells where groups agree within this many sigma (each DSM's
                                      # noise from the groups' disagreement) take their weighted
                                      # mean (0 = off)
    fusion_fill_agreeing: int = _p(1, lo=1, hi=1000)  # a hole of the best-ranked groups is filled only where this
                                      # many groups (with the one filling it) have a precise value
                                      # agreeing within fusion_agree_sigmas; 1 = any (2 trades
                                      # completeness for accuracy;
                                      # docs: research-notes.md, "The noise model of the fusion")
    fuse_weak_pair_cells: bool = _p(False)  # the fused DSM also takes cells that only a weak pair's
                                      # two-view points reach (more complete, less accurate;
                                      # docs: research-notes.md, "Weak pairs")
    icp_max_corr_m: float = _p(3.0, lo=0, lo_open=True, hi=1e4)  # ICP correspondence distance when fusing date groups
    icp_voxel_m: float = _p(1.0, lo=0, lo_open=True, hi=1e4)  # both clouds are reduced to voxel centroids of this size
    icp_max_iter: int = _p(60, lo=1, hi=100_000)  # ICP iteration cap (it stops earlier when converged)
    icp_max_source: int = _p(200_000, lo=100, hi=1e9)  # ICP keeps at most this many moving points (6 unknowns)
    icp_max_target: int = _p(500_000, lo=100, hi=1e9)  # ... and this many reference points (after voxels)
    icp_min_fitness: float = _p(0.3, lo=0, hi=1)  # below this fraction of matched points a group keeps its
                                      # GCP-based position (too little overlap to trust ICP)
    icp_sample_points: int = _p(3_000_000, lo=1000, hi=1e10)  # evenly spread points per group given to ICP and to
                                      # the grid extent (the clouds themselves are streamed)
    chunk_points: int = _p(4_000_000, lo=1000, hi=1e10)  # points per chunk when streaming clouds into the DSM
    spill_above_points: int = _p(20_000_000, lo=0, hi=1e12)  # above this many points the DSM accumulates on disk


@dataclass
class Config:
    # the sparse stage: grouping by date, tiles, features, matches, incremental SfM
    grouping: GroupingConfig = field(default_factory=GroupingConfig)
    tiling: TilingConfig = field(default_factory=TilingConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)

    # the dense stage and its matchers
    dense: DenseConfig = field(default_factory=DenseConfig)
    sgbm: SgbmConfig = field(default_factory=SgbmConfig)
    mgm: MgmConfig = field(default_factory=MgmConfig)
    pandora: PandoraConfig = field(default_factory=PandoraConfig)

    # the Euclidean upgrade and the DSM
    upgrade: UpgradeConfig = field(default_factory=UpgradeConfig)
    dsm: DsmConfig = field(default_factory=DsmConfig)

    # the whole run
    seed: int = _p(0, lo=0, hi=2**63 - 1)  # seeds every random choice (RANSAC, sampling)

    def to_dict(self) -> dict:
        return asdict(self)

    def with_overrides(self, overrides: dict) -> "Config":
        """Return a copy with "stage.field" -> value overrides applied."""
        cfg = self
        for key, value in overrides.items():
            stage, _, name = key.partition(".")
            if not name:
                cfg = replace(cfg, **{stage: value})
                continue
            sub = getattr(cfg, stage)
            if name not in {f.name for f in fields(sub)}:
                raise KeyError(f"unknown parameter {key}")
            cfg = replace(cfg, **{stage: replace(sub, **{name: value})})
        return cfg


# parameters that moved: old "section.field" -> new "section.field"
LEGACY_KEYS = {f"dense.{k}": f"sgbm.{k}" for k in ("block_size", "p1", "p2", "uniqueness",
                                                   "speckle_window", "speckle_range", "lr_max_diff_px")}
# parameters that no longer exist and never changed a result: read from older files and skipped
# (bundle.smoothness_weight and matching.min_parallax_ratio were read by nothing)
REMOVED_KEYS = {"bundle.smoothness_weight", "matching.min_parallax_ratio",
                "sfm.correction_extrapolation"}   # superseded by the bend step; acted only from a
                                                  # second correction round (1 by default)
# parameters that were removed because they did harm: read from older files only with the value
# that does what the code now does (any other value is refused, saying why)
RETIRED_KEYS: dict = {}
# parameters that change how a stage runs, not what it computes: not part of a stage's hash
# (bundle.solver: the dense and block-sparse reduced systems take the same steps to rounding,
# not bitwise: `demo`'s cameras and points differ by ~5e-10, no decision of the SfM changes)
NOT_IN_STAGE_HASH = {"dense.workers", "dense.scheduler", "dsm.chunk_points", "dsm.spill_above_points",
                     "bundle.solver"}


def config_from_dict(d: dict, *, unknown: list[str] | None = None) -> Config:
    """A Config from its to_dict() form (e.g. report.json's), renamed parameters mapped to their
    new place. Unknown parameters raise KeyError, or, given an `unknown` list, are skipped and
    appended to it so the caller can say so."""
    flat = {}
    for k, v in d.items():
        if isinstance(v, dict):
            flat.update({f"{k}.{kk}": vv for kk, vv in v.items()})
        else:
            flat[k] = v
    for old, new in LEGACY_KEYS.items():
        if old in flat and new in flat:
            raise KeyError(f"{old} and {new} are one parameter (its new name is {new}): give it once")
    cfg = Config()
    for key, v in flat.items():
        key = LEGACY_KEYS[key] if key in LEGACY_KEYS else key
        if key in REMOVED_KEYS:
            continue
        if key in RETIRED_KEYS:
            if v != RETIRED_KEYS[key][0]:
                raise KeyError(f"{key} = {v!r} is no longer possible: {RETIRED_KEYS[key][1]}")
            continue
        if isinstance(v, list):
            v = tuple(v)
        try:
            cfg = cfg.with_overrides({key: v})
        except (KeyError, TypeError, AttributeError):
            if unknown is None:
                raise KeyError(f"unknown parameter {key}") from None
            unknown.append(key)
    return cfg


PRESETS: dict[str, dict] = {
    "default": {},
    # small synthetic sites in tests: tiles small enough that tiling is exercised
    "tiny": {"tiling.tile_size": 300},
}


# What runs beyond the paper's method, each switched off by --method paper: the paper's plain
# path (tiles, SIFT, incremental affine SfM with BA per date group, SGM, H_A fitted on the GCPs
# alone, ICP fusion, DSM), kept runnable as the baseline every accuracy figure is compared with.
# The steps and their switches are declared once, in recon_core.method.CHAIN.
def _beyond_paper() -> dict:
    from recon_core.method import beyond_paper

    return beyond_paper()


BEYOND_PAPER = _beyond_paper()
METHODS: dict[str, dict] = {"default": {}, "paper": BEYOND_PAPER}


def preset(name: str, method: str = "default") -> Config:
    """The parameters of a preset (test or production sizes) under a method: "default" (what
    AE-Rec runs) or "paper" (the paper's plain path, BEYOND_PAPER switched off)."""
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    if method not in METHODS:
        raise KeyError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    return Config().with_overrides(PRESETS[name]).with_overrides(METHODS[method])


def field_comments(cls) -> dict[str, str]:
    """A config dataclass's fields -> their whole comment (the field line's and the comment
    lines under it)."""
    import inspect
    import re

    out, cur = {}, None
    for line in inspect.getsource(cls).splitlines():
        s = line.strip()
        m = re.match(r"(\w+): [^=]+=.*?#\s?(.*)$", s)
        if m:
            cur = m.group(1)
            out[cur] = m.group(2).strip()
        elif re.match(r"(\w+): [^=]+=", s):
            cur = None
        elif s.startswith("#") and cur:
            out[cur] += " " + s.lstrip("#").strip()
        elif s:
            cur = None
    return out


def config_to_toml(cfg: Config) -> str:
    """The configuration as TOML, one [section] per stage, each field with its comment (what
    `aerec config --dump` prints and `--config FILE` reads back). None is written commented."""
    import dataclasses
    import textwrap

    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, (tuple, list)):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise TypeError(f"cannot write {v!r} as TOML")

    top, parts = [], []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            com = field_comments(type(v))
            lines = [f"[{f.name}]"]
            for sf in dataclasses.fields(v):
                sv = getattr(v, sf.name)
                head = f"# {sf.name} = (none)" if sv is None else f"{sf.name} = {value(sv)}"
                text = textwrap.wrap(com.get(sf.name, ""), max(100 - len(head) - 4, 40),
                                     break_on_hyphens=False)
                lines.append(head + (f"  # {text[0]}" if text else ""))
                lines += [" " * len(head) + f"  # {t}" for t in text[1:]]
            parts.append("\n".join(lines))
        else:
            top.append(f"{f.name} = {value(v)}")
    return "\n".join(top) + "\n\n" + "\n\n".join(parts) + "\n"


MAX_CONFIG_BYTES = 1 << 20


def config_from_toml(path) -> Config:
    """A Config from a TOML file of the config_to_toml form (any subset of its fields)."""
    import tomllib
    from pathlib import Path

    from recon_core.errors import InputError

    path = Path(path)
    try:
        if not path.is_file():
            raise InputError(path, "not a configuration file (a TOML file, as `aerec config --dump` "
                                   "writes)" if path.exists() else "no such file")
        if path.stat().st_size > MAX_CONFIG_BYTES:
            raise InputError(path, f"{path.stat().st_size:,} bytes: not a configuration file "
                                   f"(a TOML file of a few KB)")
        doc = tomllib.loads(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise InputError(path, f"cannot read the configuration ({exc.strerror or exc})") from None
    except UnicodeDecodeError:
        raise InputError(path, "not a text file: a configuration is TOML (`aerec config --dump`)") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"malformed TOML ({exc})") from None
    try:
        cfg = config_from_dict(doc)
        validate(cfg)
        if cfg.upgrade.reference_dem:         # a relative path is the TOML file's
            dem = Path(cfg.upgrade.reference_dem).expanduser()
            cfg = cfg.with_overrides({"upgrade.reference_dem": str((path.parent / dem).resolve())})
        return cfg
    except KeyError as exc:
        raise InputError(path, str(exc).strip("'\"")) from None
    except (TypeError, ValueError) as exc:
        raise InputError(path, str(exc)) from None


def rule_of(section: str | None, name: str) -> Rule:
    """The Rule of field `section.name` (or of a top-level field with section None)."""
    cls = Config if section is None else type(getattr(Config(), section))
    f = {f.name: f for f in fields(cls)}[name]
    return f.metadata.get("rule", Rule())


def schema() -> dict[str, tuple[str, Rule]]:
    """'section.field' (or 'field') -> (its type annotation, its Rule), for every field."""
    out = {}
    for f in fields(Config):
        v = getattr(Config(), f.name)
        if hasattr(v, "__dataclass_fields__"):
            for g in fields(v):
                out[f"{f.name}.{g.name}"] = (str(g.type), g.metadata.get("rule", Rule()))
        else:
            out[f.name] = (str(f.type), f.metadata.get("rule", Rule()))
    return out


# relations between fields: (fields named, broken when, what is needed)
RELATIONS = (
    (("tiling.overlap", "tiling.tile_size"), lambda c: c.tiling.overlap is not None
     and c.tiling.overlap >= c.tiling.tile_size, "the overlap must be smaller than the tile size"),
    (("features.stretch_percentiles",), lambda c: not (len(c.features.stretch_percentiles) == 2
     and c.features.stretch_percentiles[0] < c.features.stretch_percentiles[1]),
     "two percentiles, the lower first"),
    (("sgbm.p2", "sgbm.p1"), lambda c: c.sgbm.p2 < c.sgbm.p1, "P2 must be >= P1 (SGM's penalties)"),
    (("mgm.p2", "mgm.p1"), lambda c: c.mgm.p2 < c.mgm.p1, "P2 must be >= P1 (MGM's penalties)"),
    (("pandora.p2", "pandora.p1"), lambda c: c.pandora.p2 <= c.pandora.p1,
     "P2 must be > P1 (SGM's penalties, as pandora_plugin_libsgm requires)"),
    (("dense.max_two_view_spread",), lambda c: 0 < c.dense.max_two_view_spread < 1,
     "must be 0 (mark no two-view point weak) or at least 1"),
    (("dense.core_margin_px", "tiling.tile_size"), lambda c: c.dense.core_margin_px * 2 >= c.tiling.tile_size,
     "the context around a tile's core must be less than half the tile size"),
    (("dense.step", "tiling.tile_size"), lambda c: c.dense.step * 8 > c.tiling.tile_size,
     "the stride must leave at least 8 reference pixels per tile side"),
    (("dsm.fusion_fill_agreeing", "dsm.fusion_agree_sigmas"),
     lambda c: c.dsm.fusion_fill_agreeing > 1 and c.dsm.fusion_agree_sigmas <= 0,
     "needs dsm.fusion_agree_sigmas > 0 (the agreement it counts)"),
    (("bundle.growing_rel_tol", "bundle.rel_tol"), lambda c: c.bundle.growing_rel_tol < c.bundle.rel_tol,
     "the growing model's tolerance must not be tighter than the final one"),
)


def validate(cfg: Config) -> None:
    """Every field against its type and its Rule, then the relations between fields, in one
    pass before any compute. Raises ValueError 'field = value: what is needed' (the caller names
    the file or option the value came from)."""
    check_types(cfg)
    for name, (_, rule) in schema().items():
        sec, _, fld = name.rpartition(".")
        v = getattr(getattr(cfg, sec), fld) if sec else getattr(cfg, fld)
        why = rule.problem(v)
        if why:
            raise ValueError(f"{name} = {v!r}: {why}")
    for names, broken, need in RELATIONS:
        if broken(cfg):
            vals = ", ".join(f"{n} = {_get(cfg, n)!r}" for n in names)
            raise ValueError(f"{vals}: {need}")


def check_extras(cfg: Config) -> None:
    """The optional packages the chosen matcher needs are installed (only asked of a run that
    reaches the dense stage: one that stops before needs none). Raises ValueError naming the
    field and the install command."""
    from recon_core.extras import missing_packages

    missing = missing_packages(cfg.dense.matcher)
    if missing:
        raise ValueError(f"dense.matcher = {cfg.dense.matcher!r}: needs {' and '.join(missing)}, not "
                         f"installed: pip install 'aerec[{cfg.dense.matcher}]'")


def _get(cfg: Config, name: str):
    sec, _, fld = name.rpartition(".")
    return getattr(getattr(cfg, sec), fld) if sec else getattr(cfg, fld)


def check_types(cfg: Config) -> None:
    """Every field holds a value of its declared type (from a file, "x" for an int would only
    fail deep inside a stage). Raises ValueError naming the field."""
    import dataclasses

    kinds = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}

    def ok(v, ann: str) -> bool:
        alts = [a.strip() for a in ann.split("|")]
        if v is None:
            return "None" in alts
        for a in alts:
            if a.startswith("tuple") and isinstance(v, (tuple, list)):
                return all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)
            if a in kinds and isinstance(v, kinds[a]) and (a == "bool" or not isinstance(v, bool)):
                return True
        return False

    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        sub = [(f"{f.name}.{g.name}", getattr(v, g.name), g.type) for g in dataclasses.fields(v)] \
            if dataclasses.is_dataclass(v) else [(f.name, v, f.type)]
        for name, val, ann in sub:
            if not ok(val, str(ann)):
                raise ValueError(f"{name} must be {ann}, not {val!r}")
