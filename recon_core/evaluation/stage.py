"""The evaluation stage: the DSM against the site's gt_dsm.tif, when it has one."""

from __future__ import annotations

from typing import TYPE_CHECKING

from recon_core.errors import AerecError
from recon_core.evaluation.evaluate import by_class, evaluate_dsm, same_cells
from recon_core.events import EventBus
from recon_core.io.files import write_json

if TYPE_CHECKING:
    from recon_core.context import RunState


def reference_dsms(site_root) -> list:
    """Other tools' DSMs of the site (SITE/ref_dsm*.tif, e.g. s2p's): scored for agreement with
    them, which is not accuracy (they are not ground truth)."""
    from pathlib import Path

    return sorted(p for p in Path(site_root).glob("ref_dsm*.tif") if p.is_file())


def run(state: RunState, bus: EventBus) -> dict:
    refs = _score_references(state, bus)
    if state.site.gt_dsm is None:
        out: dict = {"skipped": "the site has no gt_dsm.tif"}
        if refs:
            out["references"] = refs
        return out
    res = _score_truth(state, bus)
    if refs:
        res["references"] = refs
    return res


def _score_references(state, bus: EventBus) -> dict:
    lay = state.layout
    out = {}
    for ref in reference_dsms(state.site.root):
        try:
            r = evaluate_dsm(lay.dsm, ref, lay.eval_dir / ref.stem)
        except AerecError as exc:
            bus.message(f"{ref.name} not compared: {exc}", "warning")
            continue
        out[ref.name] = {k: {m: r[k][m] for m in ("median_abs_err_m", "completeness_pct", "rmse_m")
                             if m in r[k]} for k in ("aligned", "unaligned")}
        a, u = r["aligned"], r["unaligned"]
        bus.message(f"DSM vs {ref.name} (another tool's DSM: agreement, not accuracy): median |diff| "
                    f"{a['median_abs_err_m']:.3f} m, completeness (within 1 m) {a['completeness_pct']:.1f} % (aligned); "
                    f"unaligned {u['median_abs_err_m']:.3f} m, {u['completeness_pct']:.1f} %")
    return out


def _score_truth(state, bus: EventBus) -> dict:
    lay = state.layout
    res = evaluate_dsm(lay.dsm, state.site.gt_dsm, lay.eval_dir)
    a, u = res["aligned"], res["unaligned"]
    groups = {}
    for g in lay.group_dsms():             # each date group's own DSM, scored the same way
        try:
            r = evaluate_dsm(lay.group_dsm(g), state.site.gt_dsm, None)
        except AerecError as exc:            # e.g. a small group with too few cells on the GT
            groups[str(g)] = {"error": str(exc)}
            bus.message(f"group {g} alone not scored: {exc}", "warning", g)
            continue
        groups[str(g)] = {k: {m: r[k][m] for m in ("median_abs_err_m", "completeness_pct", "nmad_m")
                              if m in r[k]} for k in ("aligned", "unaligned")}
        # the fused DSM against this group on the cells both cover: fusion should not make
        # the group's own cells worse (its extra cells are mostly the hard ones)
        sc = same_cells(lay.dsm, res["alignment"], lay.group_dsm(g), r["alignment"], state.site.gt_dsm)
        groups[str(g)]["fused_vs_group_same_cells"] = sc
        same = "" if sc["a"]["median_abs_err_m"] is None else \
            (f"; on the {sc['cells_pct_of_gt']:.1f} % of cells both cover: fused "
             f"{sc['a']['median_abs_err_m']:.3f} m, group {sc['b']['median_abs_err_m']:.3f} m")
        bus.message(f"group {g} alone vs GT: median |error| {r['aligned']['median_abs_err_m']:.3f} m, "
                    f"completeness {r['aligned']['completeness_pct']:.1f} % (aligned){same}")
    if groups:
        res["groups"] = groups
    ag = score_agreement(lay, res, state.site.gt_dsm)
    if ag is not None:
        bus.message("DSM vs GT by how many date groups agree (aligned): " + "; ".join(
            f"{k}: {v['cells_pct_of_gt']:.1f} % of the GT's cells, median |error| {v['median_abs_err_m']:.3f} m"
            for k, v in ag["classes"].items()))
    if (groups or "by_agreement" in res) and res.get("outputs", {}).get("eval.json"):
        write_json(res["outputs"]["eval.json"], res)      # the viewer's Results tab reads it
    bus.message(f"DSM vs GT: median |error| {a['median_abs_err_m']:.3f} m, completeness "
                f"{a['completeness_pct']:.1f} % (aligned); unaligned {u['median_abs_err_m']:.3f} m, "
                f"{u['completeness_pct']:.1f} %")
    return res


def score_agreement(lay, res: dict, gt_path) -> dict | None:
    """The fused DSM's errors by how many date groups agree at each cell (evaluate.by_class on
    OUT/dsm_agreement.tif, with the DSM's alignment in `res`, evaluate_dsm's result), put in
    res["by_agreement"]; None when the run wrote no agreement layer (one group)."""
    if not lay.dsm_agreement.exists():
        return None
    res["by_agreement"] = by_class(lay.dsm, res["alignment"], lay.dsm_agreement, gt_path)
    return res["by_agreement"]


def load(state) -> None:
    pass
