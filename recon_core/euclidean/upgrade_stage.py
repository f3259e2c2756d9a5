"""The upgrade stage: one H_A per date group, from the run's GCP set, in one local ENU frame.

`upgrade_models` is the one function that upgrades: the pipeline's stage and the viewer's
Upgrade button both call it. The records (upgrade/) are written by this stage only: the viewer
shows its result at once, then re-runs the pipeline from this stage.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from recon_core.bend.dem import bend_kind, fit_dem_bend, open_reference_dem
from recon_core.bend.drive import BendDrive, bend_drive
from recon_core.bend.gcp import fit_gcp_bend
from recon_core.bend.metric import metric_bend, warped_model
from recon_core.bend.observability import (
    BEND_INVISIBLE_PX_PER_M,
    BendView,
    bend_observability,
    bend_seen,
    bend_warning,
)
from recon_core.config import Config
from recon_core.context import UpgradeMaps
from recon_core.errors import ReconstructionError
from recon_core.euclidean.georef import GcpAffine, frame_for, upgrade_group
from recon_core.euclidean.upgrade import UpgradeResult, flat_gcp_refusal, rescore_with_bend
from recon_core.events import EventBus
from recon_core.geometry.enu_map import BendWarp, EnuMap, EnuWarp, warp_record
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import GCP
from recon_core.io.models import load_upgrade, save_upgrade
from recon_core.model.sparse_model import SparseModel, merge_joint

if TYPE_CHECKING:
    from recon_core.context import RunState


def estimate_gsd(model, H: np.ndarray) -> float:
    """Median ground sample distance (m/px) of the registered tile cameras, via H_A."""
    Ainv = np.linalg.inv(H[:3, :3])
    gsd = []
    for t in np.flatnonzero(model.registered):
        J = model.camera(t).linear @ Ainv        # pixels per metre along E, N, U
        det = abs(np.linalg.det(J[:, :2]))
        if det > 0:
            gsd.append(1.0 / np.sqrt(det))
    if not gsd:
        raise ReconstructionError("cannot estimate the GSD: no registered camera")
    return float(np.median(gsd))


# a reference DEM tilted against the control GCPs by more than this at the site's edge is said
DEM_TILT_WARN_M = 5.0


@dataclass
class GroupUpgrade:
    """One date group's upgrade, as the stages after it and the viewer read it.

    Attributes:
        result: H_A with its report (residuals, statistics, conditioning, views).
        affine: GCP id -> GcpAffine: how each GCP was placed in the group's affine frame.
        gsd_m: ground sample distance of the group's tile cameras (m/px).
        bend: what the group's views can see of a bend (recon_core.bend.observability).
        drive: the bend to expect where they cannot see one (recon_core.bend.drive).
        warp: the metric bend step's warp (None: it stood aside or is off), and `metric` its
            summary.
        enu_warp: the bend fitted to the control GCPs or taken from the reference DEM (None:
            neither), with the summaries `gcp_bend` and `dem_bend` of those fits.
    """

    result: UpgradeResult
    affine: dict[str, GcpAffine]
    gsd_m: float
    bend: BendView | None = None
    warp: BendWarp | None = None
    metric: dict = field(default_factory=dict)
    enu_warp: EnuWarp | None = None
    gcp_bend: dict = field(default_factory=dict)
    dem_bend: dict = field(default_factory=dict)
    drive: BendDrive | None = None

    @classmethod
    def of(cls, st: ModelUpgrade, gsd_m: float) -> "GroupUpgrade":
        return cls(st.fitted, st.affine, gsd_m, st.bend, st.warp, st.metric, st.enu_warp, st.gcp_bend,
                   st.dem_bend, st.drive)

    @property
    def map(self) -> EnuMap:
        """The group's whole upgrade: the metric bend step's warp, H_A, the bend fitted to GCPs."""
        return EnuMap(self.result.H, self.warp, self.enu_warp)

    def record(self) -> dict:
        """What upgrade/group_<g>.json holds: the UpgradeResult, how each GCP was placed, GSD."""
        d = self.result.to_dict()
        d["gcp_affine"] = {k: {"xyz": None if a.xyz is None else a.xyz.tolist(), "n_images": a.n_images,
                               "reproj_rms_px": a.reproj_rms_px, "source": a.source}
                           for k, a in self.affine.items()}
        d["gsd_m"] = self.gsd_m
        if self.bend is not None:
            d["bend_observability"] = self.bend.to_dict()
        if self.drive is not None:
            d["bend_drive"] = self.drive.to_dict()
        if self.metric:
            d["metric_bend"] = self.metric
        if self.warp is not None:
            d["metric_warp"] = warp_record(self.warp)
        if self.gcp_bend:
            d["gcp_bend"] = self.gcp_bend
        if self.dem_bend:
            d["dem_bend"] = self.dem_bend
        if self.enu_warp is not None:
            d["dem_warp" if self.dem_bend.get("applied") else "gcp_warp"] = self.enu_warp.record()
        return d


@dataclass
class Upgrade:
    """The Euclidean upgrade of every group.

    Attributes:
        frame: the local ENU frame shared by all groups (at the control GCPs' centroid).
        groups: group -> GroupUpgrade of the groups that could be upgraded.
        errors: group -> why it could not be upgraded.
        joint: one H_A for all groups of one joint reconstruction.
    """

    frame: LocalFrame
    groups: dict[int, GroupUpgrade] = field(default_factory=dict)
    errors: dict[int, str] = field(default_factory=dict)
    joint: bool = False

    @property
    def results(self) -> dict[int, UpgradeResult]:
        """group -> UpgradeResult (H_A and its report) of the upgraded groups."""
        return {g: u.result for g, u in self.groups.items()}

    @property
    def Hs(self) -> dict[int, np.ndarray]:
        return {g: u.result.H for g, u in self.groups.items()}

    @property
    def maps(self) -> dict[int, EnuMap]:
        """Each group's whole upgrade (GroupUpgrade.map)."""
        return {g: u.map for g, u in self.groups.items()}

    def report(self) -> dict:
        groups = {str(g): u.record() for g, u in self.groups.items()}
        groups.update({str(g): {"error": e} for g, e in self.errors.items()})
        out = {"frame": self.frame.to_dict(), "groups": dict(sorted(groups.items()))}
        if self.joint:
            out["joint"] = ("the date groups share one joint affine reconstruction: one H_A, fitted "
                            "on every image's GCP observations, upgrades them all")
        return out


def _fit(model, gcps: list[GCP], frame: LocalFrame, cfg: Config,
         images: dict | None = None) -> tuple[UpgradeResult, dict[str, GcpAffine]]:
    """H_A of one model (held by the lines of sight of `images` whose metadata states them),
    refused (ReconstructionError) when the control GCPs and the images cannot fix its height scale."""
    res, _, aff = upgrade_group(model, gcps, frame, ransac_thresh_m=cfg.upgrade.ransac_thresh_m, seed=cfg.seed,
                                sigma_cos=cfg.upgrade.metric_prior_sigma_cos, images=images,
                                sigma_view_deg=cfg.upgrade.view_sigma_deg)
    refusal = None if cfg.upgrade.allow_flat_gcps else flat_gcp_refusal(res.conditioning)
    if refusal:
        raise ReconstructionError(refusal)
    return res, aff


@dataclass
class ModelUpgrade:
    """One model's upgrade as UPGRADE_CHAIN builds it, step by step."""

    model: SparseModel             # the model H_A is of (warped once the metric bend step applied)
    picks: list[GCP]               # the GCPs as the fit of H_A has them (picks on the cloud move
                                   # with the metric bend step's warp)
    gcps: list[GCP]                # the run's GCP set (their surveyed positions)
    frame: LocalFrame
    cfg: Config
    result: UpgradeResult | None = None
    affine: dict[str, GcpAffine] = field(default_factory=dict)
    warp: BendWarp | None = None    # the metric bend step's warp (None: it stood aside or is off)
    metric: dict = field(default_factory=dict)     # ... and its summary
    bend: BendView | None = None                   # what the views see of a bend, in the frame H_A gives
    drive: BendDrive | None = None                 # ... and the bend to expect where they see none
    enu_warp: EnuWarp | None = None  # the bend fitted to GCPs or taken from the reference DEM
    gcp_bend: dict = field(default_factory=dict)   # the GCP fit's summary
    dem_bend: dict = field(default_factory=dict)   # the reference DEM's fit's summary
    images: dict | None = None     # image name -> ImageInfo (viewing directions that hold H_A)

    @property
    def fitted(self) -> UpgradeResult:
        """The result, once H_A is fitted (every step after _h_a)."""
        assert self.result is not None
        return self.result


def _h_a(st: ModelUpgrade) -> None:
    st.result, st.affine = _fit(st.model, st.picks, st.frame, st.cfg, st.images)


def _metric_bend(st: ModelUpgrade) -> None:
    """The metric bend step (recon_core.bend.metric) and, when it applies a warp, H_A refitted
    on the warped model (GCP positions picked on the cloud move with it)."""
    if not st.cfg.upgrade.metric_bend:
        return
    fit = metric_bend(st.model, st.fitted.H, st.cfg.upgrade.orbit_altitude_km * 1e3)
    st.metric, warp = fit.summary, fit.warp
    if warp is None:
        return
    moved = warped_model(st.model, warp)
    picks = [replace(g, affine_picked={k: np.asarray(x, np.float64) + warp(np.asarray(x, np.float64)[None])[0]
                                       for k, x in g.affine_picked.items()}) for g in st.picks]
    try:
        res_w, aff_w = _fit(moved, picks, st.frame, st.cfg, st.images)
    except ReconstructionError as exc:       # e.g. the control GCPs too flat once warped
        st.metric = {**st.metric, "applied": False, "reason": f"H_A refit on the warped model: {exc}"}
        return
    st.result, st.affine, st.warp, st.model, st.picks = res_w, aff_w, warp, moved, picks


def _observe(st: ModelUpgrade) -> None:
    st.bend = bend_observability(st.model, st.fitted.H)
    st.drive = bend_drive(st.model, st.fitted.H)


def _gcp_bend(st: ModelUpgrade) -> None:
    st.result, warp, st.gcp_bend = _fit_gcp_bend(st.fitted, st.affine, st.gcps, st.frame, st.bend, st.cfg)
    if warp is not None:
        st.enu_warp = warp


def _dem_bend(st: ModelUpgrade) -> None:
    st.result, warp, st.dem_bend = _fit_dem_bend(st.fitted, st.picks, st.frame, st.model, st.bend,
                                                 st.gcp_bend, st.cfg, st.images)
    if warp is not None:
        st.enu_warp = warp


def _warn(st: ModelUpgrade) -> None:
    _warn_bend(st.fitted, st.bend, st.gcp_bend, st.dem_bend, st.drive)


# One model's upgrade, in order: H_A (with the cameras' metric constraint when asked) and the
# metric bend step (H_A refitted): the fit, which may refuse a model; then what the views can see
# of a bend in the frame H_A gives, the bend fitted to control GCPs, the vertical bend from a
# reference DEM, and the warning when nothing holds what the views cannot see. Named as
# recon_core.method.CHAIN names its steps (the two without a switch of their own are checks); a
# test holds the two in the same order.
UPGRADE_FIT = (("upgrade", _h_a), ("metric_bend", _metric_bend))
UPGRADE_HOLD = (("bend_observability", _observe), ("gcp_bend", _gcp_bend), ("dem_bend", _dem_bend),
                ("bend_warning", _warn))
UPGRADE_CHAIN = UPGRADE_FIT + UPGRADE_HOLD


def run_steps(st: ModelUpgrade, steps) -> ModelUpgrade:
    for _, step in steps:
        step(st)
    return st


def _surveyed_enu(gcps: list[GCP], frame: LocalFrame) -> np.ndarray:
    """(n, 3) the GCPs' surveyed positions in the frame's ENU."""
    return frame.geodetic_to_enu(np.array([g.llh for g in gcps]).reshape(-1, 3))


def _fit_gcp_bend(res: UpgradeResult, aff: dict[str, GcpAffine], gcps: list[GCP], frame: LocalFrame,
                  bend: BendView | None, cfg: Config) -> tuple[UpgradeResult, EnuWarp | None, dict]:
    """The bend the views cannot see, fitted to the control GCPs H_A used
    (recon_core.bend.gcp), and the result re-scored with it when it applies."""
    if not cfg.upgrade.gcp_bend:
        return res, None, {}
    pos = {k: a.xyz for k, a in aff.items() if a.xyz is not None}
    ctrl = [p["id"] for p in res.points if p["status"] in ("used", "rejected") and p["id"] in pos]
    enu = dict(zip([g.id for g in gcps], _surveyed_enu(gcps, frame)))
    thresh = cfg.upgrade.ransac_thresh_m
    fit = fit_gcp_bend(res.H, np.array([pos[k] for k in ctrl]).reshape(-1, 3),
                       np.array([enu[k] for k in ctrl]).reshape(-1, 3), bend,
                       BEND_INVISIBLE_PX_PER_M, thresh, cfg.seed)
    if not fit.applied:
        return res, None, fit.summary
    assert fit.warp is not None and fit.H is not None and fit.inliers is not None and fit.loo is not None
    used = [k for k, ok in zip(ctrl, fit.inliers) if ok]
    rejected = [k for k, ok in zip(ctrl, fit.inliers) if not ok]
    out = rescore_with_bend(res, fit.H, fit.warp, pos, enu, used, rejected, dict(zip(used, fit.loo)), fit.summary,
                  thresh)
    refusal = None if cfg.upgrade.allow_flat_gcps else flat_gcp_refusal(out.conditioning)
    if refusal:                 # the GCPs the fit kept are too flat for its height scale
        return res, None, {**fit.summary, "applied": False, "reason": f"the control GCPs it kept: {refusal}"}
    return out, fit.warp, fit.summary


def _fit_dem_bend(res: UpgradeResult, gcps: list[GCP], frame: LocalFrame, model, bend: BendView | None, gcp_fit: dict,
                  cfg: Config, images: dict | None = None,
                  max_points: int = 300_000) -> tuple[UpgradeResult, EnuWarp | None, dict]:
    """The vertical bend the views cannot see, taken from the reference DEM
    (recon_core.bend.dem) when one is given, the GCPs did not hold the bend and the
    views cannot see it; H_A refitted by the upgrade's own fit (`_fit`, on `model` with `gcps`
    as the first fit had them) on the GCPs' surveyed positions less the bend. Returns the new
    result (its residuals: against the surveyed positions less the bend there), the warp or
    None, and the summary."""
    path = cfg.upgrade.reference_dem
    if not path:
        return res, None, {}
    if (gcp_fit or {}).get("applied"):
        return res, None, {"applied": False, "reason": "the control GCPs hold the bend (gcp_bend)"}
    seen = bend_seen(bend)
    if seen:
        return res, None, {"applied": False, "reason": seen}
    assert bend is not None                  # bend_seen(None) says why not
    dem = open_reference_dem(path)
    ids = model.point_ids()
    if len(ids) > max_points:
        ids = np.sort(np.random.default_rng(cfg.seed).choice(ids, max_points, replace=False))
    enu = _surveyed_enu(gcps, frame)
    fits = {}

    def refit(warp: EnuWarp) -> np.ndarray:
        llh = frame.enu_to_geodetic(enu - warp(enu))
        moved = [replace(g, lon=float(p[0]), lat=float(p[1]), h=float(p[2])) for g, p in zip(gcps, llh)]
        fits["res"], _ = _fit(model, moved, frame, cfg, images)
        return fits["res"].H

    try:
        fit = fit_dem_bend(res.H, model.X[ids], frame, dem, bend.centre_m, bend.half_width_m,
                           refit, seed=cfg.seed, degree=cfg.upgrade.reference_dem_degree)
    except ReconstructionError as exc:        # e.g. the control GCPs too flat once moved
        return res, None, {"applied": False, "reason": f"H_A refit with the DEM's bend: {exc}"}
    info, warp = fit.summary, fit.warp
    info["dem"] = str(dem.path)
    if warp is None:
        return res, None, info
    out = fits["res"]
    note = (f"the vertical bend the views cannot see was taken from the reference DEM {dem.path.name}: a "
            f"{bend_kind(info.get('degree', 2))} "
            f"surface{' (the cubic asked for fell back: the DEM does not tell it)' if info.get('degrees_refused') else ''} of {info['bend_range_m']:.2f} m peak to peak over the site ({info['cells']} cells "
            f"of {info['cell_m']:.0f} m, scatter {info['cell_scale_m']:.2f} m; standard error at the edge "
            f"{info['bend_sigma_m']:.2f} m by a block bootstrap); H_A refitted on the control GCPs' surveyed "
            f"positions less it (the residuals are against those); the DEM's own offset and tilt "
            f"({info['offset_m']:.2f} m; {info['tilt_m'][0]:.2f} / {info['tilt_m'][1]:.2f} m at the east / north "
            "edge) are left to the GCPs")
    out.notes.append(note)
    if max(abs(v) for v in info["tilt_m"]) > DEM_TILT_WARN_M:
        out.warnings.append(f"the reference DEM {dem.path.name} is tilted against the control GCPs by "
                            f"{info['tilt_m'][0]:.1f} / {info['tilt_m'][1]:.1f} m at the site's east / north edge: "
                            "a GCP or the DEM is probably wrong (its datum is not: an offset is expected)")
    out.warnings.append(f"the reference DEM holds the vertical bend its {bend.views} views cannot see over "
                        f"{bend.site_width_km:.1f} km, not the horizontal one: positions away from the GCPs may "
                        "be off by metres (9 or more control GCPs spread over the site, or views of another "
                        "date, hold it)")
    return out, warp, info


def _picks_joint(gcp: GCP, group: int) -> GCP:
    """In a joint reconstruction every group's cloud is in one frame: a position picked on any
    group's cloud stands for the merged model's (the lowest group's pick when several)."""
    if not gcp.affine_picked or group in gcp.affine_picked:
        return gcp
    return replace(gcp, affine_picked={group: gcp.affine_picked[min(gcp.affine_picked)]})


def upgrade_models(gcps: list[GCP], models: dict, cfg: Config, images: dict | None = None) -> Upgrade:
    """Fit H_A for every group's model from one GCP set (positions picked on a group's cloud,
    GCP.affine_picked, take the place of triangulation in that group), held by the lines of
    sight of `images` (name -> ImageInfo) whose metadata states their viewing direction.

    Raises:
        ReconstructionError: no GCP at all, or no group could be upgraded (every group's reason).
    """
    if not gcps:
        raise ReconstructionError("no GCP; the Euclidean upgrade needs >= 4 control GCPs (3 with the images' viewing directions) observed "
                                  "in >= 2 images of each group")
    if not models:
        raise ReconstructionError("no sparse model to upgrade")
    up = Upgrade(frame_for(gcps))
    joint = merge_joint([models[g] for g in sorted(models)])
    if joint is not None:
        try:                                  # the whole chain: any refusal, each group apart
            st = run_steps(ModelUpgrade(joint, [_picks_joint(g, joint.group) for g in gcps], gcps, up.frame,
                                        cfg, images=images), UPGRADE_CHAIN)
            for g, model in sorted(models.items()):
                gsd = estimate_gsd(model if st.warp is None else warped_model(model, st.warp), st.fitted.H)
                up.groups[g] = GroupUpgrade.of(st, gsd)
            up.joint = True
            return up
        except ReconstructionError:           # each group on its own, below
            up = Upgrade(up.frame)
    for g, model in sorted(models.items()):
        try:                                  # a group H_A cannot be fitted for is left out
            st = run_steps(ModelUpgrade(model, gcps, gcps, up.frame, cfg, images=images), UPGRADE_FIT)
            gsd = estimate_gsd(st.model, st.fitted.H)   # a model without a registered camera stops here
        except ReconstructionError as exc:
            up.errors[g] = f"group {g}: {exc}"
            continue
        up.groups[g] = GroupUpgrade.of(run_steps(st, UPGRADE_HOLD), gsd)
    if not up.groups:
        raise ReconstructionError("; ".join(up.errors.values()))
    return up


def _warn_bend(res: UpgradeResult, bend: BendView | None, gcp_fit: dict | None = None, dem_fit: dict | None = None,
               drive: BendDrive | None = None) -> None:
    if (gcp_fit or {}).get("applied") or (dem_fit or {}).get("applied"):
        return                 # the GCPs or the reference DEM hold what the views cannot see
    text = bend_warning(bend, gcp_fit, drive)
    dem_reason = (dem_fit or {}).get("reason")
    if text and dem_reason:
        text += f"; the reference DEM could not: {dem_reason}"
    elif text:
        text += "; a coarse reference DEM of the site also holds its vertical part (upgrade.reference_dem: SRTM, Copernicus)"
    if text and text not in res.warnings:
        # check points far off the control GCPs' fit are then the bend's doing as much as a
        # wrong GCP's: say so where that warning blames the GCPs
        res.warnings[:] = [w + "; or the structure is bent (next warning)"
                           if w.startswith("the check points are off by") and "bent" not in w else w
                           for w in res.warnings]
        res.warnings.append(text)


def write(up: Upgrade, out) -> None:
    """upgrade/group_<k>.json and upgrade/frame.json (what the DSM stage reads)."""
    save_upgrade(out, {g: u.record() for g, u in up.groups.items()}, up.frame)


def run(state: RunState, bus: EventBus) -> dict:
    if not state.gcps:
        where = state.gcp_file or state.site.root / "gcps.geojson"
        raise ReconstructionError(f"{where}: no GCP; the Euclidean upgrade needs >= 4 control GCPs (3 with the images' viewing directions) "
                                  "observed in >= 2 images of each group")
    up = upgrade_models(state.gcps, state.models, state.cfg, {im.name: im for im in state.site.images})
    write(up, state.layout)
    state.upgrade = UpgradeMaps(up.maps, up.frame)
    report = up.report()
    for g, r in report["groups"].items():
        if "error" in r:
            bus.message(r["error"], "error", int(g))
        cond_warning = (r.get("conditioning") or {}).get("warning")
        said = []
        for w in r.get("warnings", []) + ([cond_warning] if cond_warning else []):
            if w not in said:
                said.append(w)
                bus.message(f"group {g}: {w}", "warning", int(g))
        db = r.get("dem_bend")
        if db and not (up.joint and g != min(report["groups"], key=int)):   # one joint map: said once
            name = Path(state.cfg.upgrade.reference_dem).name
            who = "the date groups" if up.joint else f"group {g}"
            bus.message(f"{who}: reference DEM {name}: " + (
                f"the vertical bend taken from it, {db['bend_range_m']:.2f} m peak to peak over the site "
                f"(standard error at the edge {db['bend_sigma_m']:.2f} m)" if db.get("applied")
                else f"not used ({db.get('reason')})"),
                "info" if db.get("applied") else "warning", int(g))   # asked for and unused: said even --quiet
    return report


def load(state) -> None:
    saved = load_upgrade(state.layout)
    state.upgrade = None if saved is None else UpgradeMaps(*saved)
