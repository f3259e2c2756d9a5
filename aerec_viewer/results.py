"""The Euclidean upgrade from the working GCP set, its residual table, and the DSM / error-map panel.

`run_upgrade` is what the "Upgrade" button calls: recon_core.euclidean.upgrade_stage.upgrade_models,
the function `aerec run` uses, on the working set as OUT/gcps.geojson holds it. The viewer then
re-runs the pipeline from the upgrade stage (ReconWorker.rerun_from), which writes the same
upgrade records, cloud.ply, dsm.tif and evaluation as `aerec run --redo-from upgrade`.
`DsmPanel` shows OUT/dsm.tif and the evaluation, and drapes the error map.
"""

from __future__ import annotations

import json
import weakref
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Protocol

import numpy as np

from recon_core.bend.dem import bend_kind
from recon_core.config import Config
from recon_core.context import UpgradeMaps
from recon_core.errors import ReconstructionError
from recon_core.euclidean.gcp_transfer import (
    FROM_SURVEY,
    Prediction,
    Surveyed,
    predict_from_ground,
    predict_gcp,
)
from recon_core.euclidean.upgrade_stage import Upgrade, upgrade_models
from recon_core.io.gcps import read_gcps_geojson
from recon_core.io.layout import OutLayout

from .display import DisplayTransform, euclidean_display_transform
from .gcp_session import GcpSession

if TYPE_CHECKING:
    import viser

    from recon_core.io.site import Site
    from recon_core.model.sparse_model import SparseModel

    from .gcp_controller import GcpController


@dataclass
class UpgradeOutcome(Upgrade):
    """The core's Upgrade, with the GCP session version it used (stale once the GCPs change)."""

    gcps_version: int = -1
    gcps_key: str = ""           # what the GCPs were (an undo back to them is not a change)
    # group -> the model its H_A was fitted on (weakly: a replaced model is not kept alive)
    fitted_on: dict[int, weakref.ref] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(self.results)

    def fits(self, models: dict) -> set[int]:
        """The groups whose H_A was fitted on the model they hold now: a bundle adjustment of a
        live run replaces a group's model (a new affine frame), and its H_A no longer holds."""
        return {g for g, ref in self.fitted_on.items() if g in models and ref() is models[g]}

    def transform(self, g: int) -> DisplayTransform | None:
        u = self.groups.get(g)
        return None if u is None else euclidean_display_transform(u.result.H, self.frame.origin_llh, u.warp,
                                                                  u.enu_warp)


def usable_observations(model, observations: dict) -> tuple[list[str], list[str]]:
    """(images whose observation the upgrade can use in this group: a registered tile of the
    image contains the pixel; the others, each with why not)."""
    ok, bad = [], []
    for im, (c, r) in sorted(observations.items()):
        if im not in model.images:
            continue
        if model.tiles_at(im, (c, r)):
            ok.append(im)
        elif model.tiles_at(im, (c, r), registered=False):
            bad.append(f"{im} (its tile there is not registered)")
        else:
            bad.append(f"{im} (outside every tile)")
    return ok, bad


def gcp_readiness(session: GcpSession, models: dict) -> dict[str, tuple[bool, str]]:
    """GCP id -> (can get an affine position, how): observed in >= 2 images of a group where a
    registered tile contains the pixel, or picked on a cloud. Observations the upgrade cannot use
    are named with the reason."""
    out = {}
    for g in session.gcps:
        if not g.enabled:
            out[g.id] = (False, "disabled")
            continue
        if g.affine_picked:
            out[g.id] = (True, "picked on the cloud")
            continue
        if not models:
            n = len(g.observations)
            out[g.id] = (n >= 2, f"observed in {n} image(s)")
            continue
        best = max((usable_observations(m, g.observations) for m in models.values()),
                   key=lambda ub: len(ub[0]))
        n = len(best[0])
        txt = f"observed in {n} usable image(s)" + ("" if n >= 2 else ": needs 2, or a pick on the cloud")
        if best[1]:
            txt += "; not usable: " + ", ".join(best[1])
        out[g.id] = (n >= 2, txt)
    return out


def image_group(models: dict[int, SparseModel], image: str) -> tuple[int, SparseModel] | None:
    """(group, model) of the group whose model holds `image`, or None."""
    return next(((g, m) for g, m in models.items() if image in m.images), None)


def surveyed_in(upgrade: UpgradeMaps | None, group: int, llh) -> Surveyed | None:
    """A GCP's surveyed position (lon, lat, h) with the group's upgrade map, what predicts it
    from the ground (gcp_transfer.predict_from_ground); None before the group is upgraded."""
    if upgrade is None or llh is None or group not in upgrade.maps:
        return None
    lon, lat, h = (float(v) for v in llh)
    return Surveyed((lon, lat, h), upgrade.maps[group], upgrade.frame)


def predict_in(models: dict, image: str, observations: dict, llh=None, upgrade: UpgradeMaps | None = None,
               images: dict | None = None, refine: bool = True) -> Prediction | None:
    """A GCP's prediction in `image` as the viewer shows it (gcp_transfer.predict_gcp in the
    image's group): from its observations there when 2 or more are usable, else, once the group
    is upgraded (`upgrade`, and the GCP's surveyed position `llh`), from that position, else from
    its one observation; refined by matching in `images` (name -> ImageInfo) when `refine`. None
    when no model holds the image or nothing predicts it there."""
    found = image_group(models, image)
    if found is None:
        return None
    g, model = found
    return predict_gcp(model, images or {}, observations, image, surveyed_in(upgrade, g, llh), refine=refine)


def predict_unobserved(models: dict, observations: dict, images, upgrade: UpgradeMaps | None = None,
                       llh=None) -> dict:
    """Image -> geometric Prediction (predict_in, no matching: cheap) of a GCP's pixel in each of
    `images` it is not observed in; images nothing predicts are left out. What the state table
    and the image workspace call "predicted"."""
    out = {}
    for im in images:
        pred = None if im in observations else predict_in(models, im, observations, llh, upgrade, refine=False)
        if pred is not None:
            out[im] = pred
    return out


def predict_surveyed(models: dict, images, upgrade: UpgradeMaps | None, llh) -> dict:
    """Image -> Prediction from a GCP's surveyed position alone (predict_from_ground) in each
    of `images` of an upgraded group where a registered tile sees it, observed or not: where
    the ground says it is, to set beside where the operator placed it."""
    out = {}
    for im in images:
        found = image_group(models, im)
        if found is None:
            continue
        sv = surveyed_in(upgrade, found[0], llh)
        pred = None if sv is None else predict_from_ground(found[1], sv.emap, sv.frame, sv.llh, im)
        if pred is not None:
            out[im] = pred
    return out


def residual_vectors(models: dict, observations: dict) -> dict[str, tuple[float, float]]:
    """Image -> reprojection residual (observed - reprojected, px) of a GCP's observations, in
    every group where >= 2 of them triangulate it (gcp_transfer.observation_residuals)."""
    from recon_core.euclidean.gcp_transfer import observation_residuals

    out: dict[str, tuple[float, float]] = {}
    for m in models.values():
        out.update(observation_residuals(m, observations))
    return out


def gcp_state_table(session: GcpSession, models: dict, images: list[str],
                    upgrade: UpgradeMaps | None = None) -> str:
    """Markdown table: one row per GCP, one column per image: "placed" (usable: a registered tile
    contains it), "unusable" (observed, but no registered tile there), "predicted" (not observed,
    but predictable there from its observations in that image's group: the loupe can show it),
    "predicted from survey" (not observed, predicted from its surveyed position through the
    group's `upgrade`: it has fewer than 2 observations there), "-" (neither), and "picked" (a
    cloud pick replaces the observations)."""
    if not session.gcps:
        return ""
    head = "| GCP | role | " + " | ".join(images) + " |"
    rows = [head, "|---|---|" + "---|" * len(images)]
    surveyed = False
    for g in session.gcps:
        usable: set[str] = set()
        for m in models.values():
            usable.update(usable_observations(m, g.observations)[0])
        predicted = predict_unobserved(models, g.observations, images, upgrade, g.llh)
        cells = []
        for im in images:
            if im not in g.observations:
                p = predicted.get(im)
                cells.append("-" if p is None else "predicted from survey" if p.source == FROM_SURVEY
                             else "predicted")
                surveyed |= p is not None and p.source == FROM_SURVEY
            elif not models or im in usable:
                cells.append("placed")
            else:
                cells.append("**unusable**")
        picked = " (picked)" if g.affine_picked else ""
        role = g.role if g.enabled else f"{g.role}, **disabled**"
        rows.append(f"| {g.id}{picked} | {role} | " + " | ".join(cells) + " |")
    if surveyed:
        rows.append("\n*predicted from survey*: where its surveyed position projects through the upgrade "
                    "(it has fewer than 2 observations in that date group)")
    return "\n".join(rows)


def upgrade_readiness(session: GcpSession, models: dict, images: dict, cfg) -> tuple[bool, int, int]:
    """(can the upgrade run, control GCPs usable in the best date group, how many that group
    needs), by the pipeline's own rule (recon_core.euclidean.control): the same triangulation
    and the same count; before the models, from the observations alone, as its pre-flight."""
    from recon_core.euclidean.control import control_needed, usable_before_models
    from recon_core.euclidean.georef import usable_control

    if not models:
        names = set(images)
        return False, sum(usable_before_models(g, names, 0) for g in session.gcps), \
            control_needed(list(images.values()), cfg)
    best = None
    for m in models.values():
        n = sum(why is None for why in usable_control(m, session.gcps).values())
        need = control_needed([images[k] for k in m.images if k in images], cfg)
        key = (n >= need, n - need)
        if best is None or key > best[0]:
            best = (key, n, need)
    assert best is not None                  # models is not empty
    return best[0][0], best[1], best[2]


def n_ready(session: GcpSession, models: dict, role: str | None = "control") -> int:
    """Number of GCPs (of a role) that can get an affine position."""
    ready = gcp_readiness(session, models)
    return sum(1 for g in session.gcps if ready[g.id][0] and (role is None or g.role == role))


def run_upgrade(session: GcpSession, models: dict, cfg: Config, images: dict | None = None) -> UpgradeOutcome:
    """Fit H_A for every group from the working GCP set (what the Upgrade button does), with the
    run's configuration (RANSAC threshold, seed) and the site's images (name -> ImageInfo: their
    viewing directions hold H_A), exactly as the pipeline's upgrade stage does.

    Raises:
        ReconstructionError: no model yet, or no group could be upgraded (the message of each
            group's failure, e.g. too few usable control GCPs, is in it).
    """
    if not models:
        raise ReconstructionError("no sparse model yet: wait for the sparse stage to finish")
    gcps = read_gcps_geojson(session.path)        # what a run on OUT reads: the same numbers
    up = upgrade_models(gcps, models, cfg, images)
    return UpgradeOutcome(**{f.name: getattr(up, f.name) for f in fields(up)}, gcps_version=session.version,
                          gcps_key=gcps_key(session), fitted_on={g: weakref.ref(m) for g, m in models.items()})


def images_height(outcome: "UpgradeOutcome | None", gcp) -> tuple[float, float | None] | None:
    """(the ellipsoidal height the upgrade's images put a GCP at, its sigma in metres where the
    fit knows it), from its surveyed position moved by its height residual (fitted minus
    surveyed) in the first group that has one; None when no upgrade scored it."""
    if outcome is None:
        return None
    for g in sorted(outcome.results):
        row = next((p for p in outcome.results[g].points if p["id"] == gcp.id and p.get("dU") is not None), None)
        if row is not None:
            enu = outcome.frame.geodetic_to_enu(np.array([gcp.llh]))[0] + np.array([0.0, 0.0, row["dU"]])
            return float(outcome.frame.enu_to_geodetic(enu[None])[0][2]), row.get("images_height_sigma_m")
    return None


def gcps_key(session: GcpSession) -> str:
    """A fingerprint of the GCPs' content (positions, roles, observations, picks): two sets that
    the upgrade would fit the same have the same key, whatever edits and undos lie between."""
    import hashlib
    import json

    from recon_core.io.gcps import gcps_to_geojson

    return hashlib.sha1(json.dumps(gcps_to_geojson(session.gcps), sort_keys=True, default=str).encode()).hexdigest()


def _f(v, fmt: str = "+.2f") -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)


def residual_table_markdown(result: dict) -> str:
    """The GCP residual table (control and check points) of an UpgradeResult.to_dict()."""
    rows = ["| GCP | role | status | dE m | dN m | dU m | reproj px |",
            "|---|---|---|---:|---:|---:|---:|"]
    order = {"used": 0, "rejected": 1, "check": 2, "unusable": 3}
    for p in sorted(result["points"], key=lambda p: (order.get(p["status"], 9), p["id"])):
        sus = bool(p.get("reproj_suspect"))
        px = _f(p.get("reproj_rms_px"), ".2f")
        rows.append(f"| {'**' + p['id'] + '** ⚠' if sus else p['id']} | {p['role']} | {p['status']} | "
                    f"{_f(p['dE'])} | {_f(p['dN'])} | {_f(p['dU'])} | {'**' + px + '** ⚠' if sus else px} |")
    lines = ["\n".join(rows), ""]
    for name in ("control", "check", "loo"):
        st = result["stats"].get(name) or {}
        if st.get("n"):
            lines.append(f"- **{name}** (n = {st['n']}): RMSE E {st['rmse_E_m']:.3f}, "
                         f"N {st['rmse_N_m']:.3f}, U {st['rmse_U_m']:.3f} m; "
                         f"CE90 {st['ce90_m']:.3f} m, LE90 {st['le90_m']:.3f} m")
    cond = result.get("conditioning") or {}
    lines += height_scale_lines(cond)
    if cond.get("warning"):
        lines.append(f"\n**Conditioning warning:** {cond['warning']}")
    elif cond:
        lines.append(f"- conditioning: {cond.get('level', '?')} (GCPs {cond.get('plane_rms_m', 0):.1f} m "
                     "RMS off their plane)")
    for w in result.get("warnings", []):
        if w != cond.get("warning"):
            lines.append(f"\n**Warning:** {w}")
    for n in result.get("notes", []):
        lines.append(f"\n*Note:* {n}")
    for r in result.get("rejections", []):
        lines.append(f"- {r['id']} not used: {r['reason']}")
    return "\n".join(lines)


def _loose_text(lo: dict) -> str:
    """'+-x % (y m on a 40 m roof), heights leaning +-a / +-b mm per m' of a looseness dict."""
    if lo.get("height_scale_sigma") is None:
        return "not fixed"
    lean_e, lean_n = lo.get("shear_sigma_E"), lo.get("shear_sigma_N")
    return (f"+-{100 * lo['height_scale_sigma']:.1f} % ({lo['expected_height_error_m']:.2f} m on a "
            f"{lo['structure_height_m']:.0f} m building)"
            + (f", heights leaning +-{1e3 * lean_e:.0f} / {1e3 * lean_n:.0f} mm per m east / north"
               if lean_e is not None and lean_n is not None else ""))


def height_scale_lines(cond: dict) -> list[str]:
    """What the GCPs and the images fix of the heights (the upgrade's conditioning after its
    fit), and the check point that would help most as a control point."""
    if cond.get("basis") != "fit":
        return []
    out = [f"- **heights**: the control GCPs alone fix them to {_loose_text(cond['gcp_only'])}"]
    if cond.get("with_images"):
        out.append(f"- with the {cond['images']} images' viewing directions: {_loose_text(cond['with_images'])}")
    nxt = cond.get("best_next_gcp")
    if nxt:
        out.append(f"- {nxt['id']} (now a check point) as a control point would bring the expected height "
                   f"error to {nxt['expected_height_error_m']:.2f} m")
    return out


def outcome_markdown(outcome: UpgradeOutcome) -> str:
    parts = []
    for g, r in sorted(outcome.results.items()):
        spare = (f", {r.dof} equation(s) to spare: the residuals check the GCPs" if r.dof > 0 else
                 ", no equation to spare: only check points and the pixel residuals tell")
        parts.append(f"#### Group {g}: in metres ({r.n_control_used} control GCPs{spare})\n\n"
                     + residual_table_markdown(r.to_dict()))
        doubtful = [p for p in r.points if p.get("sigma_h_m") is not None and p.get("dU") is not None]
        if doubtful:
            parts.append("Heights known only roughly (read off the DEM), as the images put them: "
                         + "; ".join(f"{p['id']} {p['dU']:+.2f} m"
                                     + ("" if p.get("images_height_sigma_m") is None else
                                        f" +- {p['images_height_sigma_m']:.2f} m")
                                     + f" (given +- {p['sigma_h_m']:.1f} m)" for p in doubtful)
                         + ". Select one and press *Take the images' height* (GCPs tab)"
                         + ("" if r.views else ": the images here do not state their viewing angles, so "
                            "these come from the other GCPs alone") + ".")
        u = outcome.groups[g]
        mb = u.metric or {}
        if mb.get("applied"):
            parts.append(f"Horizontal distortion corrected from the orbit's geometry: {mb['warp_rms_m']:.3f} m RMS "
                         f"({mb['warp_max_m']:.3f} m at most), before the GCPs' map (in the 3D view, "
                         "the DSM and cloud.ply alike).")
        gb = u.gcp_bend or {}
        if gb.get("applied"):
            mx = gb["warp_max_m"]
            what = "the views cannot see" if gb["family"] == "invisible" else "(all nine quadratic ones)"
            parts.append(f"Large-scale distortion fitted to the control GCPs ({gb['warps_fitted']} terms {what}): at most "
                         f"{mx[0]:.2f} / {mx[1]:.2f} / {mx[2]:.2f} m (E / N / U) over the site; each GCP left out is "
                         f"predicted to {gb['loo_rms_bend_m']:.2f} m RMS, against {gb['loo_rms_affine_m']:.2f} m "
                         "without it (in the 3D view, the DSM and cloud.ply alike).")
        elif gb.get("control_gcps_needed") and u.bend is not None and u.bend.site_width_km >= 1.0:
            parts.append(f"Large-scale distortion not fitted to the GCPs: {gb['reason']}.")
        db = u.dem_bend or {}
        if db.get("applied"):
            kind = bend_kind(db.get("degree", 2))
            fell = "; the cubic asked for fell back to a quadratic: the DEM does not tell it" \
                if db.get("degrees_refused") else ""
            parts.append(f"Large-scale height distortion taken from the reference DEM ({Path(db['dem']).name}), {kind}{fell}: "
                         f"{db['bend_range_m']:.2f} m peak to peak over the site, standard error "
                         f"{db['bend_sigma_m']:.2f} m at its edge (in the 3D view, the DSM and cloud.ply alike); "
                         "the horizontal one stays.")
        elif db.get("reason"):
            parts.append(f"Reference DEM not used: {db['reason']}.")
    for g, e in sorted(outcome.errors.items()):
        parts.append(f"#### Group {g}: not upgraded\n\n{e}")
    return "\n\n".join(parts)


# -- DSM and evaluation ---------------------------------------------------------------------
@dataclass(frozen=True)
class DsmProducts:
    """What OUT holds for the DSM panel."""

    dsm: Path | None
    eval_json: Path | None
    error_png: Path | None
    comparison_png: Path | None
    error_tif: Path | None = None


def find_dsm_products(out: str | Path) -> DsmProducts:
    """OUT/dsm.tif and the evaluation files of OUT (recon_core.io.layout), those that exist."""
    lay = OutLayout(out)

    def have(p: Path) -> Path | None:
        return p if p.exists() else None

    return DsmProducts(have(lay.dsm), have(lay.eval_json), have(lay.height_error_png),
                       have(lay.dsm_vs_gt_png), have(lay.height_error_tif))


def _read_reduced(ds, max_side: int, resampling=None) -> np.ndarray:
    """Band 1 of an open raster reduced by the smallest integer factor that brings its longer
    side to <= max_side (GDAL reads it from the overviews when there are any), NaN nodata."""
    f = max(1, int(np.ceil(max(ds.width, ds.height) / max_side)))
    kw = {} if resampling is None else {"resampling": resampling}
    return ds.read(1, out_shape=(max(1, ds.height // f), max(1, ds.width // f)), masked=True,
                   **kw).astype(np.float32).filled(np.nan)


def dsm_preview(dsm_path: Path, max_side: int = 640) -> np.ndarray:
    """Shaded-relief RGB of a DSM with a height colour bar (for the panel).

    Read at about twice the panel's size, from the GeoTIFF's overviews when it has them (this
    project writes COGs): a DSM of a full scene (40,000 cells a side) is never read whole."""
    import rasterio
    from rasterio.enums import Resampling

    from recon_core.evaluation import colormap as cm

    with rasterio.open(dsm_path) as ds:
        H = _read_reduced(ds, 2 * max_side, Resampling.average)
        res = abs(ds.transform.a) * ds.width / H.shape[1]
    ok = np.isfinite(H)
    lo, hi = (np.percentile(H[ok], [2, 98]) if ok.any() else (0.0, 1.0))
    rgb = cm.resize_for_display(cm.shaded(H, res, lo, hi),
                                200, max_side)
    bar = cm.colorbar(rgb.shape[0], float(lo), float(hi), lambda v: cm.sequential(v, lo, hi))
    return cm.hstack([rgb, bar])


def read_png(path: Path) -> np.ndarray:
    import cv2

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise OSError(f"cannot read {path}")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def eval_markdown(ev: dict) -> str:
    """Median error, completeness, RMSE and alignment of an evaluate_dsm result."""
    a = ev.get("aligned", {})
    al = ev.get("alignment", {})

    def g(d, *keys):
        for k in keys:
            if d.get(k) is not None:
                return d[k]
        return None

    med, comp, rmse = g(a, "median_abs_err_m"), g(a, "completeness_pct", "completeness"), g(a, "rmse_m")
    lines = ["| figure | value |", "|---|---:|",
             f"| median abs. height error | {_f(med, '.3f')} m |",
             f"| completeness (abs. error < 1 m) | {_f(comp, '.1f')} % |",
             f"| RMSE | {_f(rmse, '.3f')} m |",
             f"| alignment dx, dy, dz | {_f(al.get('dx_m'))}, {_f(al.get('dy_m'))}, "
             f"{_f(al.get('dz_m'))} m |"]
    groups = {k: v for k, v in (ev.get("groups") or {}).items() if "aligned" in v}
    if groups:
        lines += ["", "| group alone | median, m | complete | fused / group, same cells |",
                  "|---|---:|---:|---:|"]
        for k in sorted(groups, key=int):
            v = groups[k]
            sc = v.get("fused_vs_group_same_cells") or {}
            same = (f"{_f(sc['a']['median_abs_err_m'], '.3f')} / {_f(sc['b']['median_abs_err_m'], '.3f')}"
                    if sc.get("cells") else "")
            lines.append(f"| {k} | {_f(v['aligned'].get('median_abs_err_m'), '.3f')} | "
                         f"{_f(v['aligned'].get('completeness_pct'), '.1f')} % | {same} |")
    classes = (ev.get("by_agreement") or {}).get("classes") or {}
    if classes:
        lines += ["", "| groups agreeing | share of GT cells | median, m | completeness (within 1 m) |",
                  "|---|---:|---:|---:|"]
        for k in sorted(classes, key=int):
            v = classes[k]
            lines.append(f"| {k if k != '0' else '0 (weak pair, filled)'} | {_f(v['cells_pct_of_gt'], '.1f')} % | "
                         f"{_f(v['median_abs_err_m'], '.3f')} | {_f(v['within_pct'], '.1f')} % |")
    for w in ev.get("warnings", []):
        lines.append(f"\n**Warning:** {w}")
    return "\n".join(lines)


def evaluate_now(out: Path, gt: Path) -> dict:
    """Run recon_core.evaluation.evaluate.evaluate_dsm(OUT/dsm.tif, gt) into OUT/eval."""
    from recon_core.evaluation.evaluate import evaluate_dsm
    from recon_core.evaluation.stage import score_agreement
    from recon_core.io.files import write_json

    lay = OutLayout(out)
    res = evaluate_dsm(lay.dsm, gt, lay.eval_dir)
    if score_agreement(lay, res, gt) is not None:      # the DSM by how many date groups agree
        write_json(res["outputs"]["eval.json"], res)
    return res


def load_eval(p: DsmProducts) -> dict | None:
    if p.eval_json is None:
        return None
    try:
        return json.loads(p.eval_json.read_text())
    except ValueError:
        return None


def error_map_drape(error_tif: Path, frame, clip_m: float = 3.0,
                    max_side: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """The height-error raster as an RGBA texture and its 4 corners in the local ENU frame.

    Returns (rgba (h, w, 4) uint8: diverging colours clipped at +-clip_m, NaN transparent;
    corners (4, 3): top-left, top-right, bottom-right, bottom-left, ENU metres, z = 0).
    """
    import rasterio

    from recon_core.evaluation import colormap as cm
    from recon_core.geometry.geodesy import projected_to_geodetic

    with rasterio.open(error_tif) as ds:
        err = _read_reduced(ds, max_side)
        t, epsg = ds.transform, ds.crs.to_epsg()
        W, H = ds.width, ds.height
    rgba = np.dstack([cm.diverging(err, clip_m), np.where(np.isfinite(err), 235, 0).astype(np.uint8)])
    xy = np.array([t @ (0, 0), t @ (W, 0), t @ (W, H), t @ (0, H)], dtype=np.float64)
    h0 = float(frame.origin_llh[2])
    llh = projected_to_geodetic(np.column_stack([xy, np.full(4, h0)]), int(epsg))
    enu = frame.geodetic_to_enu(llh)
    enu[:, 2] = 0.0
    return rgba, enu


class DsmPanelHost(Protocol):
    """What the DSM panel needs of the viewer: where the outputs are, the site (its GT DSM),
    the server (the drape), the current frame and upgrade (the GCP controller's), and the update
    thread."""

    out: Path
    site: Site
    server: viser.ViserServer
    frame: str
    gcp: GcpController              # its `upgrade`, the last one run

    def scene_bounds(self) -> tuple[np.ndarray, np.ndarray] | None: ...
    def note(self, text: str, level: str = "info") -> None: ...
    def submit(self, fn: Callable[[], object]) -> object: ...


def provenance_markdown(out: str | Path) -> str:
    """Which GCP set and which upgrade the DSM (and its error map) come from, and when: the GCP
    file the run read (report.json), the control GCPs the upgrade used per group, the DSM's
    time, and a warning when the GCP file changed after the upgrade."""
    import datetime as _dt
    import json as _json

    from recon_core.io.layout import OutLayout

    lay = OutLayout(out)

    def utc(p: Path) -> str:
        t = _dt.datetime.fromtimestamp(p.stat().st_mtime, _dt.timezone.utc)
        return t.strftime("%Y-%m-%d %H:%M:%S UTC")

    lines = []
    if lay.dsm.exists():
        lines.append(f"Written {utc(lay.dsm)}.")
    gcp_file = None
    if lay.report.exists():
        try:
            gcp_file = _json.loads(lay.report.read_text()).get("gcp_file")
        except ValueError:
            gcp_file = None
    if gcp_file:
        gp = Path(gcp_file)
        whose = ("the viewer's working GCP set" if gp.resolve() == lay.gcps.resolve()
                 else "the site's GCPs")
        lines.append(f"GCPs: {whose} (`{gp}`).")
    newest = None
    for g in lay.upgraded_groups():
        rec_path = lay.upgrade_record(g)
        try:
            pts = _json.loads(rec_path.read_text()).get("points", [])
        except ValueError:
            continue
        used = [p["id"] for p in pts if p.get("role") == "control" and p.get("status") == "used"]
        rej = [p["id"] for p in pts if p.get("status") == "rejected"]
        txt = f"Group {g}: upgrade from {len(used)} control GCP(s) ({', '.join(used)})"
        lines.append(txt + (f", {len(rej)} left out as outliers ({', '.join(rej)})." if rej else "."))
        newest = max(newest or 0.0, rec_path.stat().st_mtime)
    if gcp_file and newest is not None and Path(gcp_file).exists() \
            and Path(gcp_file).stat().st_mtime > newest + 1e-3:
        lines.append("*The GCP file changed after this upgrade: press Upgrade to recompute the "
                     "DSM and the error map from it.*")
    return " ".join(lines)


def no_dsm_markdown(snap) -> str:
    """What the Results tab says while there is no OUT/dsm.tif: waiting, or why there is none."""
    if snap is not None and snap.status == "failed":
        text = (f"**No DSM: the {snap.failed_stage} stage failed.**" if snap.failed_stage
                else "**No DSM: the run failed.**")
        if snap.error:
            text += f" {snap.error}"
        if snap.hint:
            text += f"\n\n*What to do:* {snap.hint}"
        return text
    if snap is not None and getattr(snap, "awaiting_gcps", False) and snap.status == "done":
        from recon_core.euclidean.control import need_words

        return ("**No DSM yet: the affine reconstruction is done; the next step is yours.** Place "
                f"{need_words()} in the GCP tab, then press Upgrade: the Euclidean upgrade, the DSM and "
                "the height-error maps follow.")
    if snap is not None and snap.status in ("stopped", "done", "reopened"):
        return f"No DSM in this output folder (the run is {snap.status})."
    return "No DSM yet (OUT/dsm.tif): it appears here when the DSM stage has run."


class DsmPanel:
    """The "DSM and height error" folder of the Results tab, and the error-map drape.

    Shows OUT/dsm.tif (shaded relief with a colour bar) once the DSM stage wrote it; the
    evaluation (OUT/eval: figures and height-error map) when present, or an Evaluate button when
    only the site's gt_dsm.tif exists; drapes the error raster above the Euclidean cloud; says
    which GCP set, upgrade and time the maps come from (provenance_markdown).
    """

    def __init__(self, app: DsmPanelHost, gui):
        self.app = app
        self.drape_handle = None
        self._key = None
        with gui.add_folder("DSM and height error"):
            self.md = gui.add_markdown("No DSM yet (OUT/dsm.tif).")
            self.evaluate = gui.add_button("Evaluate the DSM against gt_dsm.tif", visible=False)
            self.dsm_img = gui.add_image(np.full((8, 8, 3), 255, np.uint8), label="DSM",
                                         visible=False)
            self.err_img = gui.add_image(np.full((8, 8, 3), 255, np.uint8),
                                         label="Height error (DSM - GT)", visible=False)
            self.drape = gui.add_checkbox("Drape the error map in the scene", False, visible=False,
                                          hint="in the Euclidean frame, just above the cloud")
            self.refresh_button = gui.add_button("Refresh")
        self.evaluate.on_click(lambda _: app.submit(self.evaluate_async))
        self.refresh_button.on_click(lambda _: app.submit(lambda: self.refresh(None, force=True)))
        self.drape.on_update(lambda _: app.submit(self.show_drape))

    def refresh(self, snap=None, force: bool = False) -> None:
        """Re-read OUT's DSM products when a stage finished (or when forced)."""
        key = None if snap is None else (tuple(sorted(snap.stages_finished)), snap.status)
        if not force and key == self._key:
            return
        self._key = key
        app = self.app
        p = find_dsm_products(app.out)
        if p.dsm is None:
            self.md.content = no_dsm_markdown(snap)
            return
        ev = load_eval(p)
        md = [f"DSM: `{p.dsm}`", provenance_markdown(app.out)]
        if ev is not None:
            md.append(eval_markdown(ev))
        elif app.site.gt_dsm is not None:
            md.append("The site has a ground-truth DSM: press Evaluate for the error map.")
        self.evaluate.visible = ev is None and app.site.gt_dsm is not None
        try:
            self.dsm_img.image = dsm_preview(p.dsm)
            self.dsm_img.visible = True
        except Exception as exc:                  # a DSM the preview cannot read: say so
            md.append(f"(cannot preview the DSM: {exc})")
        self.md.content = "\n\n".join(md)
        if p.error_png is not None:
            self.err_img.image = read_png(p.error_png)
            self.err_img.visible = True
        self.drape.visible = p.error_tif is not None

    def evaluate_async(self) -> None:
        """Evaluate OUT/dsm.tif against the site's GT on a helper thread, then refresh."""
        app = self.app
        gt = app.site.gt_dsm
        if gt is None:
            raise ReconstructionError("the site has no gt_dsm.tif")
        self.md.content += "\n\nevaluating…"

        def work() -> None:
            try:
                evaluate_now(app.out, gt)
                app.submit(lambda: self.refresh(None, force=True))
            except Exception as exc:
                msg = f"evaluation failed: {exc}"        # exc is unbound once the block ends
                app.submit(lambda: app.note(msg, "error"))

        import threading

        threading.Thread(target=work, name="aerec-evaluate", daemon=True).start()

    def show_drape(self) -> bool:
        """Show (or hide) the height-error raster as a coloured sheet just above the Euclidean
        cloud (under it, tiles and points hid it)."""
        from .display import quad_image

        app = self.app
        p = find_dsm_products(app.out)
        if self.drape_handle is not None:
            self.drape_handle.remove()
            self.drape_handle = None
        if not self.drape.value or p.error_tif is None:
            return False
        if app.frame != "euclidean" or app.gcp.upgrade is None:
            app.note("the error map is in metres: press Upgrade first (Results tab)", "warning")
            return False
        rgba, corners = error_map_drape(p.error_tif, app.gcp.upgrade.frame)
        b = app.scene_bounds()
        if b is not None:
            corners[:, 2] = float(b[1][2]) + 0.02 * float(np.ptp(corners[:, 0]))
        q = quad_image(corners, rgba, max_side=max(rgba.shape[:2]))
        self.drape_handle = app.server.scene.add_image(
            "/results/height_error", q.rgba, q.render_width, q.render_height, format="png",
            wxyz=q.wxyz, position=q.position, cast_shadow=False, receive_shadow=False)
        return True

    def frame_changed(self) -> None:
        if self.drape.value or self.drape_handle is not None:
            self.show_drape()
