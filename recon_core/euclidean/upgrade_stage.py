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

from recon_core.config import Config
from recon_core.errors import ReconstructionError
from recon_core.euclidean.dem_bend import bend_kind, fit_dem_bend, open_reference_dem
from recon_core.euclidean.gcp_bend import fit_gcp_bend, rescore
from recon_core.euclidean.georef import GcpAffine, frame_for, upgrade_group
from recon_core.euclidean.metric_bend import metric_bend, warped_model
from recon_core.euclidean.upgrade import UpgradeResult, flat_gcp_refusal
from recon_core.events import EventBus
from recon_core.geometry.affine import apply_affine_3d
from recon_core.geometry.enu_map import EnuMap, EnuWarp, warp_record
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import GCP
from recon_core.io.models import load_upgrade, save_upgrade
from recon_core.model.sparse_model import merge_joint

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


# A warp that moves the images by less than this (px RMS per metre at the site's edge) once
# each image's pushbroom model re-fits is invisible to them (3 views of one date: 1e-5 to 7e-4;
# `demo`'s 6 views of two dates: >= 0.002; `large`'s 9: >= 0.008 for every vertical warp)
BEND_INVISIBLE_PX_PER_M = 1e-3
# ... and worth a warning on sites wider than this: the bend such a warp lets through grows
# with the site (measured with 3 views: 0.4 m over 1.3 km, 1.5-2.9 m over 2.5 km)
BEND_WARN_WIDTH_KM = 1.0
# a reference DEM tilted against the control GCPs by more than this at the site's edge is said
DEM_TILT_WARN_M = 5.0


def bend_observability(model, H: np.ndarray, max_per_image: int = 20000, seed: int = 0) -> dict:
    """What a model's views can see of a bend of its structure, in the metric frame H_A gives
    (recon_core.geometry.pushbroom.warp_observability over its points, each point once per
    image, at most max_per_image per image): the singular values (px per metre of quadratic
    warp at the site's edge), each warp's vertical share, the weakest mostly vertical one, how
    many are invisible (< BEND_INVISIBLE_PX_PER_M) and the site's width. {} for a model of
    fewer than 2 images with points."""
    from recon_core.geometry.pushbroom import warp_observability

    ids = model.point_ids()
    if len(ids) < 100:
        return {}
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
        return {}
    w = warp_observability(X, images)
    s = np.asarray(w["singular_px_per_m"])
    vertical = np.linalg.norm(w["warps"][:, 6:], axis=1)
    weakest = s[vertical > 0.5]
    return {"views": len(images), "site_width_km": 2.0 * w["half_width_m"] / 1000.0,
            "singular_px_per_m": s.tolist(), "vertical_share": vertical.tolist(),
            "weakest_vertical_px_per_m": float(weakest.min()) if len(weakest) else None,
            "invisible_warps": int(np.sum(s < BEND_INVISIBLE_PX_PER_M)),
            "basis": {"warps": np.asarray(w["warps"]).tolist(), "centre_m": w["centre_m"],
                      "half_width_m": w["half_width_m"],
                      "meaning": "the warps of singular_px_per_m (rows, a-major over E, N, U x e^2, e n, "
                                 "n^2; e, n = (E, N - centre_m) / half_width_m), in the metric frame"},
            "meaning": "pixel motion (RMS, px) that each quadratic warp of the structure, 1 m at "
                       "the site's edge, leaves once every image's pushbroom model re-fits: a warp "
                       f"below {BEND_INVISIBLE_PX_PER_M:g} px per m is invisible to the images, and 4 "
                       "GCPs (an affine map) do not fix it either"}


def bend_seen(b: dict) -> str | None:
    """Why the views' bend needs nothing beyond them (they see it, or the site is too small to
    bend), or None when they cannot see a vertical bend of a site of BEND_WARN_WIDTH_KM or more
    (b: bend_observability's summary)."""
    if not b:
        return "no two views of the structure to tell a bend"
    if b["site_width_km"] < BEND_WARN_WIDTH_KM:
        return f"the site is {b['site_width_km']:.2f} km wide, too small to bend (a DEM is used from {BEND_WARN_WIDTH_KM:g} km)"
    s = b.get("weakest_vertical_px_per_m")
    if s is None or s >= BEND_INVISIBLE_PX_PER_M:
        return "the views see the bend (several dates, or views from more than one direction)"
    return None


def bend_warning(b: dict, gcp_fit: dict | None = None) -> str | None:
    """One line when the views cannot see a vertical bend of a site wider than
    BEND_WARN_WIDTH_KM (and the control GCPs did not hold it: gcp_fit, the summary of
    recon_core.euclidean.gcp_bend); None otherwise."""
    if bend_seen(b):
        return None
    s = b["weakest_vertical_px_per_m"]
    text = (f"its {b['views']} views cannot see a bend of the structure (a height warp of 1 m over "
            f"its {b['site_width_km']:.1f} km moves them by {s:.0e} px): 4 GCPs fix an affine map, not a "
            "bend, so heights away from the GCPs may be off by metres (3 views of one date: 1.5-2.9 m "
            "over 2.5 km, 30 m RMS over 10 km); views of another date, or more control GCPs spread "
            "over the site, hold it")
    need = (gcp_fit or {}).get("control_gcps_needed")
    if need and gcp_fit.get("control_gcps", 0) < need:
        text += f" ({need} or more control GCPs fit the {gcp_fit['invisible_warps']} warps it cannot see)"
    if (gcp_fit or {}).get("loo_rms_bend_m") is not None:
        text += f"; {gcp_fit['reason']}"
    return text


@dataclass
class Upgrade:
    """The Euclidean upgrade of every group.

    Attributes:
        frame: the local ENU frame shared by all groups (at the control GCPs' centroid).
        results: group -> UpgradeResult of the groups that could be upgraded.
        affine: group -> {GCP id: GcpAffine}: how each GCP was placed in that group's frame.
        gsd_m: group -> ground sample distance of its tile cameras (m/px).
        errors: group -> why it could not be upgraded.
    """

    frame: LocalFrame
    results: dict[int, UpgradeResult] = field(default_factory=dict)
    affine: dict[int, dict[str, GcpAffine]] = field(default_factory=dict)
    gsd_m: dict[int, float] = field(default_factory=dict)
    errors: dict[int, str] = field(default_factory=dict)
    joint: bool = False           # one H_A for all groups of one joint reconstruction
    bend: dict[int, dict] = field(default_factory=dict)   # group -> bend_observability
    warps: dict[int, object] = field(default_factory=dict)  # group -> the metric bend step's BendWarp
    metric: dict[int, dict] = field(default_factory=dict)   # group -> the metric bend step's summary
    enu_warps: dict[int, EnuWarp] = field(default_factory=dict)  # group -> the bend fitted to GCPs
    gcp_bend: dict[int, dict] = field(default_factory=dict)  # group -> that fit's summary
    dem_bend: dict[int, dict] = field(default_factory=dict)  # group -> the reference DEM's fit's summary

    @property
    def Hs(self) -> dict[int, np.ndarray]:
        return {g: r.H for g, r in self.results.items()}

    @property
    def maps(self) -> dict[int, EnuMap]:
        """Each group's whole upgrade: the metric bend step's warp, H_A, the bend fitted to GCPs."""
        return {g: EnuMap(r.H, self.warps.get(g), self.enu_warps.get(g)) for g, r in self.results.items()}

    def record(self, g: int) -> dict:
        """What upgrade/group_<g>.json holds: the UpgradeResult, how each GCP was placed, GSD."""
        d = self.results[g].to_dict()
        d["gcp_affine"] = {k: {"xyz": None if a.xyz is None else a.xyz.tolist(), "n_images": a.n_images,
                               "reproj_rms_px": a.reproj_rms_px, "source": a.source}
                           for k, a in self.affine[g].items()}
        d["gsd_m"] = self.gsd_m[g]
        if self.bend.get(g):
            d["bend_observability"] = self.bend[g]
        if self.metric.get(g):
            d["metric_bend"] = self.metric[g]
        if self.warps.get(g) is not None:
            d["metric_warp"] = warp_record(self.warps[g])
        if self.gcp_bend.get(g):
            d["gcp_bend"] = self.gcp_bend[g]
        if self.dem_bend.get(g):
            d["dem_bend"] = self.dem_bend[g]
        if self.enu_warps.get(g) is not None:
            key = "dem_warp" if self.dem_bend.get(g, {}).get("applied") else "gcp_warp"
            d[key] = self.enu_warps[g].record()
        return d

    def report(self) -> dict:
        groups = {str(g): self.record(g) for g in self.results}
        groups.update({str(g): {"error": e} for g, e in self.errors.items()})
        out = {"frame": self.frame.to_dict(), "groups": dict(sorted(groups.items()))}
        if self.joint:
            out["joint"] = ("the date groups share one joint affine reconstruction: one H_A, fitted "
                            "on every image's GCP observations, upgrades them all")
        return out


def _fit(model, gcps: list[GCP], frame: LocalFrame, cfg: Config) -> tuple[UpgradeResult, dict[str, GcpAffine]]:
    """H_A of one model, refused (ReconstructionError) when the control GCPs are too flat."""
    res, _, aff = upgrade_group(model, gcps, frame, ransac_thresh_m=cfg.upgrade.ransac_thresh_m, seed=cfg.seed,
                                sigma_cos=cfg.upgrade.metric_prior_sigma_cos)
    refusal = None if cfg.upgrade.allow_flat_gcps else flat_gcp_refusal(res.conditioning)
    if refusal:
        raise ReconstructionError(refusal)
    return res, aff


@dataclass(frozen=True)
class MetricFit:
    """H_A after the metric bend step: the fit, the GCP placements, the step's warp (None when
    it stood aside or is off) and summary, the model H_A is of (warped when the step applied) and
    the GCPs as that fit had them (picks on the cloud moved with the warp)."""

    result: UpgradeResult
    affine: dict
    warp: object | None
    summary: dict
    model: object
    gcps: list


def _fit_metric(model, gcps: list[GCP], frame: LocalFrame, cfg: Config) -> MetricFit:
    """_fit, then the metric bend step (recon_core.euclidean.metric_bend) and, when it applies a
    warp, H_A refitted on the warped model (GCP positions picked on the cloud move with it)."""
    res, aff = _fit(model, gcps, frame, cfg)
    if not cfg.upgrade.metric_bend:
        return MetricFit(res, aff, None, {}, model, gcps)
    warp, info = metric_bend(model, res.H, cfg.upgrade.orbit_altitude_km * 1e3)
    if warp is None:
        return MetricFit(res, aff, None, info, model, gcps)
    moved = warped_model(model, warp)
    picks = [replace(g, affine_picked={k: np.asarray(x, np.float64) + warp(np.asarray(x, np.float64)[None])[0]
                                       for k, x in g.affine_picked.items()}) for g in gcps]
    try:
        res_w, aff_w = _fit(moved, picks, frame, cfg)
    except ReconstructionError as exc:       # e.g. the control GCPs too flat once warped
        return MetricFit(res, aff, None, {**info, "applied": False,
                                          "reason": f"H_A refit on the warped model: {exc}"}, model, gcps)
    return MetricFit(res_w, aff_w, warp, info, moved, picks)


def _surveyed_enu(gcps: list[GCP], frame: LocalFrame) -> np.ndarray:
    """(n, 3) the GCPs' surveyed positions in the frame's ENU."""
    return frame.geodetic_to_enu(np.array([g.llh for g in gcps]).reshape(-1, 3))


def _fit_gcp_bend(res: UpgradeResult, aff: dict[str, GcpAffine], gcps: list[GCP], frame: LocalFrame,
                  bend: dict, cfg: Config) -> tuple[UpgradeResult, EnuWarp | None, dict]:
    """The bend the views cannot see, fitted to the control GCPs H_A used
    (recon_core.euclidean.gcp_bend), and the result re-scored with it when it applies."""
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
    used = [k for k, ok in zip(ctrl, fit.inliers) if ok]
    rejected = [k for k, ok in zip(ctrl, fit.inliers) if not ok]
    out = rescore(res, fit.H, fit.warp, pos, enu, used, rejected, dict(zip(used, fit.loo)), fit.summary,
                  thresh)
    refusal = None if cfg.upgrade.allow_flat_gcps else flat_gcp_refusal(out.conditioning)
    if refusal:                 # the GCPs the fit kept are too flat for its height scale
        return res, None, {**fit.summary, "applied": False, "reason": f"the control GCPs it kept: {refusal}"}
    return out, fit.warp, fit.summary


def _fit_dem_bend(res: UpgradeResult, gcps: list[GCP], frame: LocalFrame, model, bend: dict, gcp_fit: dict,
                  cfg: Config, max_points: int = 300_000) -> tuple[UpgradeResult, EnuWarp | None, dict]:
    """The vertical bend the views cannot see, taken from the reference DEM
    (recon_core.euclidean.dem_bend) when one is given, the GCPs did not hold the bend and the
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
    dem = open_reference_dem(path)
    ids = model.point_ids()
    if len(ids) > max_points:
        ids = np.sort(np.random.default_rng(cfg.seed).choice(ids, max_points, replace=False))
    enu = _surveyed_enu(gcps, frame)
    fits = {}

    def refit(warp: EnuWarp) -> np.ndarray:
        llh = frame.enu_to_geodetic(enu - warp(enu))
        moved = [replace(g, lon=float(p[0]), lat=float(p[1]), h=float(p[2])) for g, p in zip(gcps, llh)]
        fits["res"], _ = _fit(model, moved, frame, cfg)
        return fits["res"].H

    basis = bend["basis"]
    try:
        H, warp, info = fit_dem_bend(res.H, model.X[ids], frame, dem, basis["centre_m"], basis["half_width_m"],
                                     refit, seed=cfg.seed, degree=cfg.upgrade.reference_dem_degree)
    except ReconstructionError as exc:        # e.g. the control GCPs too flat once moved
        return res, None, {"applied": False, "reason": f"H_A refit with the DEM's bend: {exc}"}
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
    out.warnings.append(f"the reference DEM holds the vertical bend its {bend['views']} views cannot see over "
                        f"{bend['site_width_km']:.1f} km, not the horizontal one: positions away from the GCPs may "
                        "be off by metres (9 or more control GCPs spread over the site, or views of another "
                        "date, hold it)")
    return out, warp, info


def _picks_joint(gcp: GCP, group: int) -> GCP:
    """In a joint reconstruction every group's cloud is in one frame: a position picked on any
    group's cloud stands for the merged model's (the lowest group's pick when several)."""
    if not gcp.affine_picked or group in gcp.affine_picked:
        return gcp
    return replace(gcp, affine_picked={group: gcp.affine_picked[min(gcp.affine_picked)]})


def upgrade_models(gcps: list[GCP], models: dict, cfg: Config) -> Upgrade:
    """Fit H_A for every group's model from one GCP set (positions picked on a group's cloud,
    GCP.affine_picked, take the place of triangulation in that group).

    Raises:
        ReconstructionError: no GCP at all, or no group could be upgraded (every group's reason).
    """
    if not gcps:
        raise ReconstructionError("no GCP; the Euclidean upgrade needs >= 4 control GCPs observed "
                                  "in >= 2 images of each group")
    if not models:
        raise ReconstructionError("no sparse model to upgrade")
    up = Upgrade(frame_for(gcps))
    joint = merge_joint([models[g] for g in sorted(models)])
    if joint is not None:
        try:
            mf = _fit_metric(joint, [_picks_joint(g, joint.group) for g in gcps], up.frame, cfg)
            res, aff, warp, info, moved, used = mf.result, mf.affine, mf.warp, mf.summary, mf.model, mf.gcps
            bend = bend_observability(moved, res.H)
            res, gwarp, ginfo = _fit_gcp_bend(res, aff, gcps, up.frame, bend, cfg)
            res, dwarp, dinfo = _fit_dem_bend(res, used, up.frame, moved, bend, ginfo, cfg)
            gwarp = gwarp if dwarp is None else dwarp
            _warn_bend(res, bend, ginfo, dinfo)
            for g, model in sorted(models.items()):
                up.results[g], up.affine[g] = res, aff
                up.gsd_m[g] = estimate_gsd(model if warp is None else warped_model(model, warp), res.H)
                up.bend[g], up.warps[g], up.metric[g] = bend, warp, info
                up.gcp_bend[g] = ginfo
                if dinfo:
                    up.dem_bend[g] = dinfo
                if gwarp is not None:
                    up.enu_warps[g] = gwarp
            up.joint = True
            return up
        except ReconstructionError:           # each group on its own, below
            up = Upgrade(up.frame)
    for g, model in sorted(models.items()):
        try:
            mf = _fit_metric(model, gcps, up.frame, cfg)
            res, aff, warp, info, moved, used = mf.result, mf.affine, mf.warp, mf.summary, mf.model, mf.gcps
            estimate_gsd(moved, res.H)            # a model without a registered camera stops here
        except ReconstructionError as exc:
            up.errors[g] = f"group {g}: {exc}"
            continue
        up.affine[g] = aff
        up.warps[g], up.metric[g] = warp, info
        up.bend[g] = bend_observability(moved, res.H)
        res, gwarp, up.gcp_bend[g] = _fit_gcp_bend(res, aff, gcps, up.frame, up.bend[g], cfg)
        res, dwarp, dinfo = _fit_dem_bend(res, used, up.frame, moved, up.bend[g], up.gcp_bend[g], cfg)
        if dinfo:
            up.dem_bend[g] = dinfo
        gwarp = gwarp if dwarp is None else dwarp
        up.results[g], up.gsd_m[g] = res, estimate_gsd(moved, res.H)
        if gwarp is not None:
            up.enu_warps[g] = gwarp
        _warn_bend(res, up.bend[g], up.gcp_bend[g], dinfo)
    if not up.results:
        raise ReconstructionError("; ".join(up.errors.values()))
    return up


def _warn_bend(res: UpgradeResult, bend: dict, gcp_fit: dict | None = None, dem_fit: dict | None = None) -> None:
    if (gcp_fit or {}).get("applied") or (dem_fit or {}).get("applied"):
        return                 # the GCPs or the reference DEM hold what the views cannot see
    text = bend_warning(bend, gcp_fit)
    if text and (dem_fit or {}).get("reason"):
        text += f"; the reference DEM could not: {dem_fit['reason']}"
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
    save_upgrade(out, {g: up.record(g) for g in up.results}, up.frame)


def run(state: RunState, bus: EventBus) -> dict:
    if not state.gcps:
        where = state.gcp_file or state.site.root / "gcps.geojson"
        raise ReconstructionError(f"{where}: no GCP; the Euclidean upgrade needs >= 4 control GCPs "
                                  "observed in >= 2 images of each group")
    up = upgrade_models(state.gcps, state.models, state.cfg)
    write(up, state.layout)
    state.upgrade = (up.maps, up.frame)
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
                else f"not used ({db.get('reason')})"), "info", int(g))
    return report


def load(state) -> None:
    state.upgrade = load_upgrade(state.layout)
