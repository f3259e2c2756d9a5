"""Runs the stages in order, writes OUT, emits events; resumes from the last finished stage.

Each finished stage records itself in OUT/stages/<stage>.json (with a hash of the
configuration); a later run with the same configuration skips it and reloads its outputs.
OUT/report.json gathers every stage's summary and is rewritten atomically after each stage.
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path

from .config import Config
from .errors import InputError, ReconstructionError
from .events import EventBus, Message, StageDone
from .grouping import Group, group_by_date
from .io_utils import write_json
from .site import Site, load_site, read_gcps_geojson

STAGES = ("sparse", "dense", "upgrade", "dsm", "eval")
# Configuration sections each stage depends on (its own and upstream ones): a stage is redone
# only when one of these changed (or, for "upgrade", the GCP file).
STAGE_SECTIONS = {
    "sparse": ("grouping", "tiling", "features", "matching", "sfm", "bundle", "seed"),
    "dense": ("dense",),
    "upgrade": ("upgrade",),
    "dsm": ("dsm",),
    "eval": (),
}


@dataclass
class RunState:
    """What the stages pass on to each other (loaded back when resuming)."""

    site: Site
    out: Path
    cfg: Config
    groups: list[Group]
    models: dict = field(default_factory=dict)      # group index -> SparseModel
    dense: dict = field(default_factory=dict)       # group index -> dense.ply path
    upgrade: tuple | None = None                    # ({group: H_A}, LocalFrame)
    report: dict = field(default_factory=dict)


def config_hash(cfg: Config) -> str:
    return hashlib.sha1(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode()).hexdigest()[:12]


def gcp_source(site: Site, out: Path) -> Path:
    """The GCP file a run uses: OUT/gcps.geojson (the viewer's working set) when it exists,
    else the site's own gcps.geojson."""
    own = Path(out) / "gcps.geojson"
    return own if own.exists() else site.root / "gcps.geojson"


def stage_hash(cfg: Config, stage: str, site: Site, out: Path | None = None) -> str:
    """Hash of what a stage's result depends on: its and its upstream stages' parameters, and
    for the upgrade and later stages the GCP file's content."""
    d = cfg.to_dict()
    keys = [k for s in STAGES[: STAGES.index(stage) + 1] for k in STAGE_SECTIONS[s]]
    blob = {k: d[k] for k in keys}
    if STAGES.index(stage) >= STAGES.index("upgrade"):
        gcp_file = gcp_source(site, out) if out is not None else site.root / "gcps.geojson"
        blob["gcps"] = gcp_file.read_text() if gcp_file.exists() else ""
    return hashlib.sha1(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _stage_file(out: Path, stage: str) -> Path:
    return out / "stages" / f"{stage}.json"


def stage_done(out: Path, stage: str, cfg: Config, site: Site) -> bool:
    f = _stage_file(out, stage)
    if not f.exists():
        return False
    try:
        return json.loads(f.read_text()).get("stage_hash") == stage_hash(cfg, stage, site, out)
    except ValueError:
        return False


def _mark_done(state: RunState, stage: str, summary: dict) -> None:
    write_json(_stage_file(state.out, stage), {"stage_hash": stage_hash(state.cfg, stage, state.site, state.out),
                                               "summary": summary})
    state.report.setdefault("stages", {})[stage] = summary
    write_json(state.out / "report.json", state.report)


def run_sparse(state: RunState, bus: EventBus) -> dict:
    from .sparse import reconstruct_group, save_model

    out = {"groups": {}}
    for g in state.groups:
        try:
            model, summary = reconstruct_group(g, state.cfg, bus)
        except ReconstructionError as exc:
            bus.emit(Message("error", str(exc), g.index))
            out["groups"][str(g.index)] = {"error": str(exc), "images": [im.name for im in g.images]}
            continue
        save_model(model, state.out)
        state.models[g.index] = model
        out["groups"][str(g.index)] = summary
    if not state.models:
        msgs = "; ".join(v["error"] for v in out["groups"].values())
        raise ReconstructionError(f"no group could be reconstructed: {msgs}")
    return out


def load_sparse(state: RunState) -> None:
    from .sparse import group_dir, load_model

    for g in state.groups:
        if (group_dir(state.out, g.index) / "cameras.json").exists():
            state.models[g.index] = load_model(state.out, g.index)


def run_dense(state: RunState, bus: EventBus) -> dict:
    from .dense import dense_path, reconstruct_dense_group

    out = {"groups": {}}
    images = {im.name: im for im in state.site.images}
    for g, model in sorted(state.models.items()):
        path = dense_path(state.out, g)
        _, summary = reconstruct_dense_group(model, images, state.cfg.dense, bus, path=path)
        state.dense[g] = path
        out["groups"][str(g)] = summary
    return out


def load_dense(state: RunState) -> None:
    from .dense import dense_path

    for g in state.models:
        if dense_path(state.out, g).exists():
            state.dense[g] = dense_path(state.out, g)


def run_upgrade(state: RunState, bus: EventBus) -> dict:
    from .euclidean import upgrade_groups

    Hs, frame, report = upgrade_groups(state.site, state.models, state.cfg, state.out)
    state.upgrade = (Hs, frame)
    for g, r in report["groups"].items():
        if "error" in r:
            bus.message(r["error"], "error", int(g))
        for w in r.get("warnings", []) + ([r["conditioning"]["warning"]] if r.get("conditioning", {}).get("warning") else []):
            bus.message(f"group {g}: {w}", "warning", int(g))
    return report


def load_upgrade_state(state: RunState) -> None:
    from .euclidean import load_upgrade

    state.upgrade = load_upgrade(state.out)


def run_dsm(state: RunState, bus: EventBus) -> dict:
    from .euclidean import make_dsm

    if state.upgrade is None:
        raise ReconstructionError("the DSM needs the upgrade stage")
    Hs, frame = state.upgrade
    from .euclidean import PointSource

    sources = {}
    for g in Hs:
        src = PointSource(ply=state.dense[g]) if g in state.dense else None
        if src is not None and len(src):
            sources[g] = src
        elif g in state.models:
            m = state.models[g]
            ids = m.point_ids()
            sources[g] = PointSource(m.X[ids], m.gray[ids])
            bus.message(f"group {g}: no dense cloud, the DSM uses the sparse points", "warning", g)
    ups = state.report.get("stages", {}).get("upgrade", {}).get("groups", {})
    gsd = min((v["gsd_m"] for v in ups.values() if "gsd_m" in v), default=0.5)
    return make_dsm(state.site, sources, Hs, frame, gsd, state.cfg, state.out, bus)


def run_eval(state: RunState, bus: EventBus) -> dict:
    from .evaluate import evaluate_dsm

    if state.site.gt_dsm is None:
        return {"skipped": "the site has no gt_dsm.tif"}
    res = evaluate_dsm(state.out / "dsm.tif", state.site.gt_dsm, state.out / "eval")
    a, u = res["aligned"], res["unaligned"]
    bus.message(f"DSM vs GT: median |error| {a['median_abs_err_m']:.3f} m, completeness "
                f"{a['completeness_pct']:.1f} % (aligned); unaligned {u['median_abs_err_m']:.3f} m, "
                f"{u['completeness_pct']:.1f} %")
    return res


def _noop_loader(state: RunState) -> None:
    pass


STAGE_RUNNERS = {"sparse": (run_sparse, load_sparse), "dense": (run_dense, load_dense),
                 "upgrade": (run_upgrade, load_upgrade_state), "dsm": (run_dsm, _noop_loader),
                 "eval": (run_eval, _noop_loader)}


def run(site_path: str | Path, out: str | Path, cfg: Config | None = None, *,
        until: str | None = None, bus: EventBus | None = None, resume: bool = True,
        redo_from: str | None = None) -> RunState:
    """Run the pipeline on a site up to and including stage `until` (default: all).

    Finished stages are reloaded when `resume` (unless their parameters changed); `redo_from`
    recomputes that stage and every later one.
    """
    cfg = cfg or Config()
    bus = bus or EventBus()
    site = load_site(site_path)
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "output path exists and is not a folder")
    out.mkdir(parents=True, exist_ok=True)
    gcp_path = gcp_source(site, out)
    if gcp_path != site.root / "gcps.geojson":
        site.gcps = read_gcps_geojson(gcp_path, {im.name: im for im in site.images})
        bus.emit(Message("info", f"GCPs from {gcp_path} (the viewer's working set), not the site's file"))
    groups = group_by_date(site.images, cfg.grouping.max_gap_days, cfg.grouping.max_span_days)
    report_path = out / "report.json"
    report = json.loads(report_path.read_text()) if (resume and report_path.exists()) else {}
    report.update({"site": str(site.root.resolve()), "gcp_file": str(gcp_path.resolve()), "config": cfg.to_dict(), "config_hash": config_hash(cfg),
                   "groups": [{"index": g.index, "images": [im.name for im in g.images],
                               "span_days": g.span_days} for g in groups]})
    state = RunState(site, out, cfg, groups, report=report)
    for name in (until, redo_from):
        if name is not None and name not in STAGES:
            raise InputError(None, f"unknown stage {name!r}; stages are {', '.join(STAGES)}")
    first_redo = STAGES.index(redo_from) if redo_from else len(STAGES)
    last = STAGES.index(until) if until else len(STAGES) - 1
    for stage in STAGES[: last + 1]:
        runner, loader = STAGE_RUNNERS[stage]
        if resume and STAGES.index(stage) < first_redo and stage_done(out, stage, cfg, site):
            loader(state)
            bus.emit(Message("info", f"{stage}: already done, reloaded from {out}"))
            continue
        t0 = time.time()
        summary = runner(state, bus)
        summary["seconds"] = time.time() - t0
        _mark_done(state, stage, summary)
        bus.emit(StageDone(stage, summary["seconds"], summary))
    return state
