"""Resume: what each finished stage depended on, and whether a run can reload it.

Each finished stage records itself in OUT/stages/<stage>.json with a hash of what it depends on
(its and its upstream stages' configuration sections, the site's inputs by content, and for the
upgrade and later stages the GCP file's content, the images' viewing directions and the
reference DEM); a later run with the same hash reloads it instead of recomputing it.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING

from recon_core.config import NOT_IN_STAGE_HASH, Config
from recon_core.io.files import write_json
from recon_core.io.fingerprint import content_hash
from recon_core.io.gcps import working_gcp_file
from recon_core.io.layout import OutLayout
from recon_core.io.site import Site

if TYPE_CHECKING:
    from recon_core.context import RunState


# the stages in their order (recon_core.pipeline.STAGE_MODULES runs them)
STAGES = ("sparse", "dense", "upgrade", "dsm", "eval")


# Configuration sections each stage depends on (its own and upstream ones): a stage is redone
# only when one of these changed (or, for "upgrade" and later, the GCP file).
STAGE_SECTIONS = {
    "sparse": ("grouping", "tiling", "features", "matching", "sfm", "bundle", "seed"),
    "dense": ("dense", "sgbm"),
    "upgrade": ("upgrade",),
    "dsm": ("dsm",),
    "eval": (),
}


def config_hash(cfg: Config) -> str:
    return hashlib.sha1(json.dumps(cfg.to_dict(), sort_keys=True, default=str).encode()).hexdigest()[:12]


def stage_hash(cfg: Config, stage: str, site: Site, out: Path | None = None,
               gcp_text: str | None = None) -> str:
    """Hash of what a stage's result depends on: its and its upstream stages' parameters (less
    those that only change how it runs: workers, chunk sizes), and for the upgrade and later
    stages the GCP file's content (`gcp_text`, else the file the run would read now)."""
    d = cfg.to_dict()
    keys = [k for s in STAGES[: STAGES.index(stage) + 1] for k in STAGE_SECTIONS[s]]
    # the dense stage also depends on its matcher's own section (sgbm's is listed: runs made
    # before there was a choice keep their hashes)
    if STAGES.index(stage) >= STAGES.index("dense") and cfg.dense.matcher not in keys:
        keys.append(cfg.dense.matcher)
    blob = {k: ({f: v for f, v in d[k].items() if f"{k}.{f}" not in NOT_IN_STAGE_HASH}
                if isinstance(d[k], dict) else d[k]) for k in keys}
    blob["inputs"] = site_fingerprint(site, out)
    if stage == "eval":
        blob["scored_against"] = scored_against(site)
    if STAGES.index(stage) >= STAGES.index("upgrade"):
        if gcp_text is None:
            gcp_file = working_gcp_file(site.root, out) if out is not None else site.root / "gcps.geojson"
            gcp_text = gcp_file.read_text() if gcp_file.exists() else ""
        blob["gcps"] = gcp_text
        views = {im.name: im.view.to_dict() for im in site.images if im.view is not None}
        if views:                   # the images' viewing directions hold the upgrade's height scale
            blob["views"] = views
        dem = cfg.upgrade.reference_dem
        if dem:                     # a DEM replaced in place makes the upgrade stale
            blob["reference_dem"] = ([Path(dem).stat().st_size, content_hash(dem)]
                                     if Path(dem).is_file() else None)
    return hashlib.sha1(json.dumps(blob, sort_keys=True, default=str).encode()).hexdigest()[:12]


def site_fingerprint(site: Site, out: Path | None = None) -> dict:
    """What identifies a site's inputs for resume: each image's name, size, a hash of all its
    bytes (recon_core.io.fingerprint: pixels edited in place, whatever the modification time
    says, are other inputs; a copied or touched site keeps its fingerprint) and acquisition
    time (a sidecar added or edited regroups the dates), and site.json's hints (another image,
    another folder's images, another time or a changed resolution_m make every stage stale). The
    configuration enters through its values, the GCP file from the upgrade on."""
    from recon_core.io.fingerprint import HashCache

    hashes = HashCache(out)
    imgs = []
    for im in site.images:
        st = Path(im.path).stat()
        when = None if im.acquired is None else im.acquired.isoformat()
        imgs.append([im.name, st.st_size, hashes(im.path), when, im.time_source])
    hashes.save()
    return {"images": imgs, "site_json": site.hints}


def scored_against(site: Site) -> list:
    """What the evaluation stage reads besides OUT: the ground truth and other tools' DSMs."""
    from recon_core.evaluation.stage import reference_dsms

    scored = [p for p in [site.gt_dsm, *reference_dsms(site.root)] if p is not None]
    return [[p.name, p.stat().st_size, content_hash(p)] for p in scored]


def products(out: Path, stage: str) -> dict[str, int]:
    """What a stage wrote, as it is now: each file's path under OUT -> its size in bytes (the
    files of a folder it wrote, each)."""
    lay = OutLayout(out)
    found: dict[str, int] = {}
    for p in lay.stage_products(stage):
        for f in (sorted(q for q in p.rglob("*") if q.is_file()) if p.is_dir() else [p]):
            found[f.relative_to(lay.root).as_posix()] = f.stat().st_size
    return found


def stage_done(out: Path, stage: str, cfg: Config, site: Site, gcp_text: str | None = None) -> bool:
    """Does OUT hold this stage's result for this configuration, site and GCP set: its record
    with the same hash, and every file it recorded as written still there with its size (a
    product deleted or replaced since is made again; records of older versions list none)?"""
    f = OutLayout(out).stage_record(stage)
    if not f.exists():
        return False
    try:
        rec = json.loads(f.read_text())
    except ValueError:
        return False
    if not isinstance(rec, dict) or rec.get("stage_hash") != stage_hash(cfg, stage, site, out, gcp_text):
        return False
    wrote = rec.get("products")
    if not isinstance(wrote, dict):          # a record of an older version: its main product at least
        return bool(OutLayout(out).stage_products(stage)) and (stage != "dsm" or OutLayout(out).dsm.exists())
    now = products(out, stage)
    return all(now.get(k) == v for k, v in wrote.items())


def finished_stages(out: Path, cfg: Config, site: Site) -> set[str]:
    """The stages a run with this configuration would reload rather than recompute."""
    return {s for s in STAGES if stage_done(out, s, cfg, site)}


def mark_done(state: RunState, stage: str, summary: dict) -> None:
    """Record a finished stage: its hash of what it depended on and its summary, in
    OUT/stages/<stage>.json and OUT/report.json."""
    # the GCP set as the run read it at its start, not the file as it may be now
    h = stage_hash(state.cfg, stage, state.site, state.out, gcp_text=state.gcp_text)
    write_json(state.layout.stage_record(stage), {"stage_hash": h, "summary": summary,
                                                  "products": products(state.out, stage)})
    state.report.setdefault("stages", {})[stage] = summary
    write_json(state.layout.report, state.report)
