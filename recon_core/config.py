"""All parameters of a run, one dataclass per stage, each field commented.

Named presets (`PRESETS`) tune them for test-size and production-size inputs.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace


@dataclass
class GroupingConfig:
    max_gap_days: float = 15.0        # images closer in time than this share a date group
    max_span_days: float | None = 30.0  # cap on a chained group's total span (None = no cap)


@dataclass
class TilingConfig:
    tile_size: int = 1000             # d: tile side in pixels (pushbroom ~ affine on a tile)
    overlap: int | None = None        # overlap between neighbouring tiles; None = d // 3


@dataclass
class FeatureConfig:
    max_features_per_mpx: int = 30000  # SIFT keypoints kept per megapixel (strongest first)
    contrast_threshold: float = 0.01  # SIFT contrast threshold on the 8-bit detection image
    detect_block: int = 2048          # images are read by window of this many pixels
    stretch_percentiles: tuple[float, float] = (0.5, 99.5)  # uint16 -> 8-bit robust stretch
    refine_half_px: int = 7           # tie points refined by least-squares patch matching on
                                      # (2 h + 1)^2 px patches against a view of their track
                                      # of the same date
                                      # (SIFT's own positions are off by ~0.35 px); 0 = off
    refine_min_ncc: float = 0.7       # a refined position needs this patch correlation


@dataclass
class MatchingConfig:
    ratio: float = 0.8                # Lowe's ratio test
    mutual: bool = True               # keep only mutual nearest neighbours
    fa_thresh_px: float = 1.5         # RANSAC threshold of the affine fundamental matrix (px)
    fa_ransac_iters: int = 500        # cap on its RANSAC samples (adaptive below it)
    min_inliers: int = 30             # a tile pair with fewer verified matches is dropped
    coarse_factor: int = 8            # downsampling of the whole-image overview match
    k_partners: int = 6               # match each image with its k best partners only
    min_parallax_ratio: float = 0.0   # sigma3/sigma4 guard; 0 = adaptive (see sfm)


@dataclass
class SfmConfig:
    resect_thresh_px: float = 2.0     # RANSAC threshold for tile resection
    resect_ransac_iters: int = 500    # cap on its RANSAC samples (adaptive below it)
    image_camera_thresh_factor: float = 4.0  # one camera fitted to a whole image (the prior of a
                                      # flat tile) departs from the pushbroom by a few pixels:
                                      # its RANSAC threshold is this many times resect_thresh_px
    resect_min_inliers: int = 12      # a tile needs this many 2D-3D inliers to register
    max_reproj_px: float = 2.0        # triangulated points with a larger error are dropped
    min_points_conditioning: float = 0.01  # resection points flatter than this are regularised
    min_triangulation_ratio: float = 0.3  # drop points whose conditioning (~ B/H of their views) is below
                                      # this fraction of the model's 90th percentile (0 = off)
    init_min_parallax: float = 3.0    # sigma3/sigma4 of an initial tile pair's matches below
                                      # this: no usable parallax (the measurement matrix is near rank 2)
    init_min_inliers: int = 60        # the initial tile pair needs at least this many verified matches
    global_ba_growth: float = 0.15    # run a global BA when tiles grew by this fraction
    local_ba_window: int = 6          # cameras refined in a local BA after each registration
    joint_groups: bool = True         # reconstruct all date groups in one affine frame when their
                                      # images match across dates (each group keeps its tiles and
                                      # points): all views hold the structure against bending;
                                      # falls back to one reconstruction per group otherwise
    joint_min_matches: int = 200      # verified matches an image needs with the other groups'
                                      # images for the joint reconstruction
    joint_partners: int = 2           # images of other groups each image is matched with
    tie_sigma_px: float = 0.01        # the per-image pushbroom tie (recon_core.sparse.image_model)
                                      # in the final global adjustments: the model's error against
                                      # a pushbroom, px, for a model of 3 images; n > 3 images
                                      # scale it by 3 / n (more views check the tie) (0 = off)
    correction_rounds: int = 1        # closing global adjustments after the first tied one, each
                                      # with the within-tile correction refitted (each image's
                                      # pushbroom model's departure from affine inside a tile
                                      # taken out of its observations: what drives the bend;
                                      # recon_core.geometry.pushbroom), in a joint reconstruction
                                      # of several dates (one pass's views cannot see the vertical
                                      # warps it would free) (0 = none; each round more lowers
                                      # the bend further and costs one global adjustment)
    correction_extrapolation: float = 1.0  # from the second round
                                      # on, each round's correction is pushed this many times its
                                      # change since the round before, g + w (g - g_prev): plain
                                      # rounds converge slowly, each removing less of the bend
                                      # (0 = plain rounds; at most 1: 2 diverged; README,
                                      # "Extrapolated rounds")


@dataclass
class BundleConfig:
    loss: str = "huber"               # robust loss of scipy.optimize.least_squares
    loss_scale_px: float = 1.0        # f_scale of the robust loss, pixels
    max_nfev: int = 50                # LM iteration cap of a global adjustment
    local_max_nfev: int = 10          # LM iteration cap of a local adjustment (after each tile)
    rel_tol: float = 1e-6             # an adjustment stops when an iteration lowers the robust
                                      # cost by less than this fraction of it ...
    growing_rel_tol: float = 1e-5     # ... and this one while the model grows (local and
                                      # intermediate global adjustments): the final global
                                      # adjustments converge to rel_tol from there
    solver: str = "auto"              # reduced camera system: dense (Cholesky), sparse (8 x 8
                                      # blocks, SuperLU: 10-20 km sites) or auto (sparse from
                                      # 1,500 camera unknowns)


@dataclass
class DenseConfig:
    step: int = 1                     # stride of the reference-pixel grid (1 = every pixel)
    matcher: str = "sgbm"             # stereo matcher (recon_core.dense.matchers.MATCHERS); its
                                      # parameters are the config section of the same name
    disp_margin_px: float = 8.0       # margin added around the sparse disparity percentiles
    disp_margin_frac: float = 0.25    # ... plus this fraction of the percentile range
    min_pair_matches: int = 20        # a tile pair needs this many sparse matches to be matched
    min_parallax_ratio: float = 3.0   # sigma3/sigma4 of the pair's sparse matches (baseline test)
    max_two_view_spread: float = 2.0  # a two-view point whose pair triangulates more than this
                                      # many times less precisely than the group's best pair is
                                      # marked weak: a DSM cell uses it only when no other point
                                      # falls there (0 = mark none)
    core_margin_px: int = 48          # context matched around the part of a tile it owns (px)
    ncc_radius: int = 2               # photometric check patch radius (5 x 5 patches)
    min_ncc: float = 0.3              # links with a lower NCC are dropped
    max_reproj_px: float = 1.0        # views with a larger error are dropped from a track
    view_drop_rounds: int = 3         # rounds of dropping a track's worst view and re-triangulating
    workers: int | None = None        # local worker processes (None = all cores, 1 = serial)
    scheduler: str | None = None      # dask.distributed scheduler address (None = local pool)


@dataclass
class SgbmConfig:
    """OpenCV StereoSGBM (3-way) with a true left-right check (a second run on the mirrored pair)."""

    block_size: int = 5               # matching block (odd)
    p1: int = 8                       # smoothness penalty P1, times block_size^2
    p2: int = 32                      # smoothness penalty P2, times block_size^2
    uniqueness: int = 10              # uniqueness ratio (%)
    speckle_window: int = 100         # speckle filter: max region size (px) to remove
    speckle_range: int = 2            # speckle filter: max disparity variation (px)
    lr_max_diff_px: float = 1.0       # left-right consistency tolerance (px)


@dataclass
class UpgradeConfig:
    ransac_thresh_m: float = 2.0      # GCP inlier threshold of the H_A RANSAC (metres)
    allow_flat_gcps: bool = False     # go on when the control GCPs of a group are (nearly) on one
                                      # plane: expected height error > 10 m on a 40 m structure
    metric_prior_sigma_cos: float = 2e-3  # the cameras' metric constraint in the fit of H_A: the
                                      # cosine between a tile camera's rows in metres, per image
                                      # (recon_core.euclidean.metric_prior; 0 = GCPs only)
    metric_bend: bool = True          # the metric bend step (recon_core.euclidean.metric_bend): the
                                      # horizontal warp no affine frame lets the views see, found once
                                      # H_A gives metres, each image's 1D perspective from its orbit
    gcp_bend: bool = True             # fit the bend the views cannot see to >= 9 control GCPs
                                      # (recon_core.euclidean.gcp_bend): kept only when it
                                      # predicts each control GCP left out better than H_A alone
    orbit_altitude_km: float = 694.0  # its start: the orbit's altitude (Pleiades, SPOT 6/7: 694;
                                      # Pleiades Neo, WorldView-3: ~620); the step then estimates one
                                      # common change of the ranges from the data (10 % off: harmless)
    reference_dem: str = ""           # a coarse DEM of the site (GeoTIFF: SRTM, Copernicus GLO-30, a
                                      # national DEM; any CRS, geoid or ellipsoid heights) that holds
                                      # the vertical bend the views cannot see when the GCPs do not
                                      # (recon_core.euclidean.dem_bend); "" = none
    reference_dem_degree: int = 2     # the degree of the vertical bend taken from it: 2 (a dome or a
                                      # saddle) or 3, for a DEM whose errors do not reach over km
                                      # (Copernicus GLO-30 class): on `wide` (10 km, one date) 3 gives
                                      # check U 1.98 m instead of 2.95 m with such a DEM, but 5.69
                                      # instead of 3.55 m with errors correlated over 1 km (SRTM class)


@dataclass
class DsmConfig:
    resolution_m: float | None = None  # output cell size; None = site.json's, else the GSD
    stat: str = "median"              # per-cell statistic: median | upper_median | max
    fill_holes_px: int = 2            # fill only holes this small (radius, cells) with support
    laz: bool = True                  # also write cloud.laz (LAS 1.4 with the CRS) from cloud.ply
    fusion_correction_m: float = 32.0  # a lower-ranked group is brought onto the fused surface by
                                      # a smooth correction (medians of the difference in blocks
                                      # of this size) before it fills holes; 0 = off
    fusion_agree_sigmas: float = 2.5   # cells where groups agree within this many sigma (each DSM's
                                      # noise from the groups' disagreement) take their weighted
                                      # mean (0 = off)
    fusion_fill_agreeing: int = 1     # a hole of the best-ranked groups is filled only where this
                                      # many groups (with the one filling it) have a precise value
                                      # agreeing within fusion_agree_sigmas; 1 = any. wide3: 0.677 m
                                      # / 57.6 % with 1, 0.603 m / 53.6 % with 2 (best group 0.613
                                      # m / 52.0 %); large: 0.261 m / 73.3 % with 1, 0.211 m / 55.7 %
                                      # with 2 (best group 0.301 m / 64.6 %)
    fuse_weak_pair_cells: bool = False  # the fused DSM also takes cells that only a weak pair's
                                      # two-view points reach (1.2 m median error on `demo`:
                                      # fused 0.179 m / 73.9 % without, 0.202 m / 76.9 % with)
    icp_max_corr_m: float = 3.0       # ICP correspondence distance when fusing date groups
    icp_voxel_m: float = 1.0          # both clouds are reduced to voxel centroids of this size
    icp_max_iter: int = 60            # ICP iteration cap (it stops earlier when converged)
    icp_max_source: int = 200_000     # ICP keeps at most this many moving points (6 unknowns)
    icp_max_target: int = 500_000     # ... and this many reference points (after voxels)
    icp_min_fitness: float = 0.3      # below this fraction of matched points a group keeps its
                                      # GCP-based position (too little overlap to trust ICP)
    icp_sample_points: int = 3_000_000  # evenly spread points per group given to ICP and to
                                      # the grid extent (the clouds themselves are streamed)
    chunk_points: int = 4_000_000     # points per chunk when streaming clouds into the DSM
    spill_above_points: int = 20_000_000  # above this many points the DSM accumulates on disk


@dataclass
class Config:
    grouping: GroupingConfig = field(default_factory=GroupingConfig)
    tiling: TilingConfig = field(default_factory=TilingConfig)
    features: FeatureConfig = field(default_factory=FeatureConfig)
    matching: MatchingConfig = field(default_factory=MatchingConfig)
    sfm: SfmConfig = field(default_factory=SfmConfig)
    bundle: BundleConfig = field(default_factory=BundleConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    sgbm: SgbmConfig = field(default_factory=SgbmConfig)
    upgrade: UpgradeConfig = field(default_factory=UpgradeConfig)
    dsm: DsmConfig = field(default_factory=DsmConfig)
    seed: int = 0                     # seeds every random choice (RANSAC, sampling)

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
# (bundle.smoothness_weight was read by nothing)
REMOVED_KEYS = {"bundle.smoothness_weight"}
# parameters that were removed because they did harm: read from older files only with the value
# that does what the code now does (any other value is refused, saying why)
RETIRED_KEYS = {"sfm.bend_step": (False, "the bend step was removed: on sensors whose focal plane "
                                  "is not one straight line (every real one) it bent the structure")}
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
    cfg = Config()
    for key, v in flat.items():
        key = LEGACY_KEYS.get(key, key)
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
BEYOND_PAPER = {
    "features.refine_half_px": 0,          # tie points refined by patch matching
    "sfm.joint_groups": False,             # all date groups in one affine frame
    "sfm.tie_sigma_px": 0.0,               # the per-image pushbroom tie
    "sfm.correction_rounds": 0,            # the within-tile correction
    "upgrade.metric_prior_sigma_cos": 0.0,  # the cameras' metric constraint in H_A's fit
    "upgrade.metric_bend": False,          # the metric bend step
    "upgrade.gcp_bend": False,             # the bend fitted to >= 9 control GCPs
    "upgrade.reference_dem": "",           # the vertical bend from a reference DEM
}
METHODS: dict[str, dict] = {"default": {}, "paper": BEYOND_PAPER}


def preset(name: str, method: str = "default") -> Config:
    """The parameters of a preset (test or production sizes) under a method: "default" (what
    AE-Rec runs) or "paper" (the paper's plain path, BEYOND_PAPER switched off)."""
    if name not in PRESETS:
        raise KeyError(f"unknown preset {name!r}; choose from {sorted(PRESETS)}")
    if method not in METHODS:
        raise KeyError(f"unknown method {method!r}; choose from {sorted(METHODS)}")
    return Config().with_overrides(PRESETS[name]).with_overrides(METHODS[method])


def config_to_toml(cfg: Config) -> str:
    """The configuration as TOML, one [section] per stage, each field with its comment (what
    `aerec config --dump` prints and `--config FILE` reads back). None is written commented."""
    import dataclasses
    import inspect

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

    def comments(cls) -> dict[str, str]:
        out = {}
        for line in inspect.getsource(cls).splitlines():
            name, _, rest = line.strip().partition(":")
            if "#" in rest and name.isidentifier():
                out[name] = rest.split("#", 1)[1].strip()
        return out

    top, parts = [], []
    for f in dataclasses.fields(cfg):
        v = getattr(cfg, f.name)
        if dataclasses.is_dataclass(v):
            com = comments(type(v))
            lines = [f"[{f.name}]"]
            for sf in dataclasses.fields(v):
                sv = getattr(v, sf.name)
                c = f"  # {com[sf.name]}" if sf.name in com else ""
                lines.append(f"# {sf.name} = (none){c}" if sv is None else f"{sf.name} = {value(sv)}{c}")
            parts.append("\n".join(lines))
        else:
            top.append(f"{f.name} = {value(v)}")
    return "\n".join(top) + "\n\n" + "\n\n".join(parts) + "\n"


def config_from_toml(path) -> Config:
    """A Config from a TOML file of the config_to_toml form (any subset of its fields)."""
    import tomllib
    from pathlib import Path

    from recon_core.errors import InputError

    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except OSError as exc:
        raise InputError(path, f"cannot read the configuration ({exc.strerror or exc})") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, f"malformed TOML ({exc})") from None
    try:
        cfg = config_from_dict(doc)
        check_types(cfg)
        if cfg.upgrade.reference_dem:         # a relative path is the TOML file's
            dem = Path(cfg.upgrade.reference_dem).expanduser()
            cfg = cfg.with_overrides({"upgrade.reference_dem": str((path.parent / dem).resolve())})
        return cfg
    except KeyError as exc:
        raise InputError(path, str(exc).strip("'\"")) from None
    except (TypeError, ValueError) as exc:
        raise InputError(path, f"bad value ({exc})") from None


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
