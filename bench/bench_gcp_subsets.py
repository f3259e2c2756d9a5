"""Accuracy over many choices of control GCPs: does a result depend on lucky GCP geometry?
Prints one table; asserts nothing.

    python bench/bench_gcp_subsets.py                          # omaha, reunion, gizeh, demo
    python bench/bench_gcp_subsets.py --sites omaha --n 40 --sizes 4,3 --label after
    python bench/bench_gcp_subsets.py --table-only             # reprint from results_*.json

For each site a finished run (sparse and dense, made once under --root/<site>/out with the
defaults) is redone from the upgrade once per control subset: the subset's GCPs are the
control points of the run's working GCP set (OUT/gcps.geojson), every other GCP of the site a
check point. Subsets of --sizes GCPs: all of them when there are at most --n, else --n drawn
at random with a fixed seed (--seed); the site's own control set is run too. Each subset runs
the pre-flight and the pipeline up to the DSM (`until="dsm"`), then the fused DSM is scored
against the site's ground truth (omaha_3dates, synthetic presets) or s2p's DSM (the real
Pleiades pairs: agreement, not accuracy).

The sites are read, never copied: each is a folder under --root/sites whose images/ holds
links to the shared site's images, with a sidecar per image giving its acquisition time (the
image's own TIFFTAG_DATETIME) and, where the shared site has views.json, its viewing
direction (`view`, the site format's optional member), as a vendor's metadata states it.

Per site and subset size, printed: the refusal rate; the median and 90th percentile of the DSM's
median error (ME) and completeness (CP, cells within 1 m), aligned; the median and 90th
percentile of the check points' RMSE E / N / U; the best subset's ME; the site's own control
set. Results go to --root/results_<label>.json (one entry per site, size and subset), so that
runs of two versions of the code (`--label before`, `--label after`) print side by side.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from itertools import combinations
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

SHARED = ROOT.parent / "shared" / "data"
# site name -> (shared folder, tile size, reference DSM file or None for gt_dsm.tif)
REAL = {"omaha": ("omaha_3dates", None, None),
        "reunion": ("reunion_pair", 400, "ref_dsm_s2p.tif"),
        "gizeh": ("gizeh_pair", 300, "ref_dsm_s2p.tif")}


def linked_site(name: str, root: Path) -> tuple[Path, int | None, Path] | None:
    """(site folder, tile size, reference DSM) of a site, made under root/sites on first use;
    None when the shared data is absent."""
    if name not in REAL:
        return synthetic_site(name, root)
    folder, tile, ref = REAL[name]
    src = SHARED / folder
    if not src.is_dir():
        return None
    site = root / "sites" / name
    if not (site / "images").is_dir():
        import rasterio

        tmp = site.with_name(site.name + ".part")
        (tmp / "images").mkdir(parents=True, exist_ok=True)
        views = json.loads((src / "views.json").read_text()) if (src / "views.json").exists() else {}
        for img in sorted((src / "images").iterdir()):
            if img.suffix.lower() not in (".tif", ".tiff"):
                continue
            (tmp / "images" / img.name).symlink_to(img.resolve())
            with rasterio.open(img) as ds:
                stamp = ds.tags().get("TIFFTAG_DATETIME")
            when = stamp.replace(":", "-", 2).replace(" ", "T") + "Z"
            side = {"acquired": when}
            if img.name in views:
                side["view"] = views[img.name]
            (tmp / "images" / (img.stem + ".json")).write_text(json.dumps(side, indent=1))
        for f in ("gcps.geojson", "site.json", "gt_dsm.tif", "ref_dsm_s2p.tif"):
            if (src / f).exists():
                (tmp / f).symlink_to((src / f).resolve())
        tmp.rename(site)
    reference = site / (ref or "gt_dsm.tif")
    return site, tile, reference


def synthetic_site(name: str, root: Path) -> tuple[Path, int | None, Path]:
    from recon_core.synthetic.generator import generate_site

    site = root / "sites" / name
    if not (site / "site.json").exists():
        t0 = time.time()
        generate_site(site, preset=name, seed=0)
        print(f"generated {name} in {time.time() - t0:.0f} s -> {site}", flush=True)
    add_views(site)
    return site, (300 if name.startswith("tiny") else None), site / "gt_dsm.tif"


def add_views(site: Path) -> None:
    """A site generated before the generator wrote the images' viewing directions: add them to
    the sidecars as it now writes them (from the site's truth/, as a vendor states them), so that
    its images, and its runs, stay the same."""
    try:
        from recon_core.synthetic.generator import load_truth_cameras, load_truth_scene
    except ImportError:                        # an older version of the code: nothing to add
        return
    cams = load_truth_cameras(site)
    if not hasattr(next(iter(cams.values())), "centre_view"):
        return
    h0 = load_truth_scene(site).h0
    for name, cam in cams.items():
        side = site / "images" / (Path(name).stem + ".json")
        doc = json.loads(side.read_text())
        if "view" not in doc:
            doc["view"] = cam.centre_view(h0)
            side.write_text(json.dumps(doc, indent=1))


def subsets(n: int, size: int, count: int, seed: int) -> list[tuple[int, ...]]:
    """All size-subsets of range(n) when there are at most `count`, else `count` distinct ones
    drawn at random (fixed seed)."""
    total = math.comb(n, size)
    if total <= count:
        return list(combinations(range(n), size))
    rng = np.random.default_rng(seed)
    seen: dict[tuple[int, ...], None] = {}
    while len(seen) < count:
        seen[tuple(sorted(rng.choice(n, size, replace=False).tolist()))] = None
    return list(seen)


def write_roles(site: Path, out: Path, control: set[str]) -> None:
    """OUT/gcps.geojson: the site's GCPs with `control` as control points, the rest as checks."""
    doc = json.loads((site / "gcps.geojson").read_text())
    for f in doc["features"]:
        f["properties"]["role"] = "control" if f["properties"]["id"] in control else "check"
    tmp = out / "gcps.geojson.tmp"
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(out / "gcps.geojson")


def run_subset(site: Path, out: Path, cfg, reference: Path, control: set[str]) -> dict:
    """One subset: pre-flight, the pipeline from the upgrade to the DSM, the DSM's scores."""
    from recon_core.errors import InputError, ReconstructionError
    from recon_core.evaluation.evaluate import evaluate_dsm
    from recon_core.events import EventBus
    from recon_core.pipeline import run
    from recon_core.preflight import preflight

    write_roles(site, out, control)
    t0 = time.time()
    try:
        preflight(site, out, cfg)
        state = run(site, out, cfg, until="dsm", bus=EventBus(lambda ev: None), redo_from="upgrade")
    except (InputError, ReconstructionError) as exc:
        return {"refused": str(exc).splitlines()[0][:300], "seconds": time.time() - t0}
    up = state.report["stages"]["upgrade"]["groups"]
    checks = [(u["stats"]["check"]["rmse_E_m"], u["stats"]["check"]["rmse_N_m"], u["stats"]["check"]["rmse_U_m"])
              for u in up.values() if (u.get("stats") or {}).get("check", {}).get("n")]
    errors = [u["error"] for u in up.values() if "error" in u]
    ev = evaluate_dsm(out / "dsm.tif", reference, None)
    row = {"aligned": [ev["aligned"]["median_abs_err_m"], ev["aligned"]["completeness_pct"]],
           "unaligned": [ev["unaligned"]["median_abs_err_m"], ev["unaligned"]["completeness_pct"]],
           "check_enu": [float(np.mean([c[i] for c in checks])) for i in range(3)] if checks else None,
           "groups_refused": errors, "seconds": time.time() - t0}
    cond = [u.get("conditioning") or {} for u in up.values() if "error" not in u]
    if cond and cond[0].get("expected_height_error_m") is not None:
        row["expected_height_error_m"] = cond[0]["expected_height_error_m"]
    return row


def prepare(name: str, root: Path):
    """(site, OUT, configuration, reference, GCP ids, the site's control ids) with sparse and
    dense done, or None when the site is absent."""
    from recon_core.config import preset
    from recon_core.events import EventBus
    from recon_core.pipeline import run

    found = linked_site(name, root)
    if found is None:
        print(f"{name}: absent, skipped", flush=True)
        return None
    site, tile, reference = found
    cfg = preset("default")
    if tile:
        cfg = cfg.with_overrides({"tiling.tile_size": tile})
    out = root / name / "out"
    out.mkdir(parents=True, exist_ok=True)
    (out / "gcps.geojson").unlink(missing_ok=True)
    t0 = time.time()
    run(site, out, cfg, until="dense", bus=EventBus(lambda ev: None))
    print(f"{name}: sparse and dense ready ({time.time() - t0:.0f} s)", flush=True)
    feats = json.loads((site / "gcps.geojson").read_text())["features"]
    ids = [f["properties"]["id"] for f in feats]
    own = tuple(i for i, f in enumerate(feats) if f["properties"].get("role", "control") == "control")
    return site, out, cfg, reference, ids, own


def pct(values, q):
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.percentile(v, q)) if v else float("nan")


def summary(rows: dict) -> dict:
    """Refusal rate, median and 90th percentile of ME, CP and check E / N / U over subsets."""
    done = [r for r in rows.values() if "refused" not in r]
    out = {"n": len(rows), "refused": len(rows) - len(done)}
    if done:
        me = [r["aligned"][0] for r in done]
        cp = [r["aligned"][1] for r in done]
        out.update(me_med=pct(me, 50), me_p90=pct(me, 90), me_best=min(me), cp_med=pct(cp, 50),
                   cp_p10=pct(cp, 10))
        chk = [r["check_enu"] for r in done if r.get("check_enu")]
        if chk:
            out["check_med"] = [pct([c[i] for c in chk], 50) for i in range(3)]
            out["check_p90"] = [pct([c[i] for c in chk], 90) for i in range(3)]
    return out


def fmt(v, spec=".3f"):
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, spec)


def print_table(root: Path, sites: list[str]) -> None:
    labels = sorted(p.stem[len("results_"):] for p in root.glob("results_*.json"))
    stores = {lab: json.loads((root / f"results_{lab}.json").read_text()) for lab in labels}
    print("\n| site | GCPs | code | refused | ME median / p90 (m) | best ME | CP median / p10 (%) | "
          "check E / N / U median (m) | check E / N / U p90 (m) | the site's own control set: ME / CP; check E / N / U |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for site in sites:
        for size in ("4", "3"):
            for lab in labels:
                rows = {k: v for k, v in stores[lab].get(site, {}).get(size, {}).items() if k != "own"}
                if not rows:
                    continue
                s = summary(rows)
                own = stores[lab].get(site, {}).get(size, {}).get("own")
                own_txt = "-"
                if own and "refused" not in own:
                    own_txt = (f"{fmt(own['aligned'][0])} m / {fmt(own['aligned'][1], '.1f')} %; "
                               + (" / ".join(fmt(x, ".2f") for x in own["check_enu"]) if own.get("check_enu") else "-"))
                elif own:
                    own_txt = "refused"
                cm, c9 = s.get("check_med"), s.get("check_p90")
                print(f"| {site} | {size} of {len(rows)} | {lab} | {s['refused']} / {s['n']} "
                      f"({100 * s['refused'] / s['n']:.0f} %) | {fmt(s.get('me_med'))} / {fmt(s.get('me_p90'))} | "
                      f"{fmt(s.get('me_best'))} | {fmt(s.get('cp_med'), '.1f')} / {fmt(s.get('cp_p10'), '.1f')} | "
                      f"{' / '.join(fmt(x, '.2f') for x in cm) if cm else '-'} | "
                      f"{' / '.join(fmt(x, '.2f') for x in c9) if c9 else '-'} | {own_txt} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sites", default="omaha,reunion,gizeh,demo")
    ap.add_argument("--sizes", default="4,3", help="subset sizes")
    ap.add_argument("--n", type=int, default=40, help="subsets per size (all when fewer exist)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--label", default="current", help="the name of this version of the code")
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_gcp_subsets"))
    ap.add_argument("--table-only", action="store_true")
    args = ap.parse_args(argv)
    sites = args.sites.split(",")
    args.root.mkdir(parents=True, exist_ok=True)
    if not args.table_only:
        store_path = args.root / f"results_{args.label}.json"
        store = json.loads(store_path.read_text()) if store_path.exists() else {}
        for name in sites:
            ready = prepare(name, args.root)
            if ready is None:
                continue
            site, out, cfg, reference, ids, own = ready
            for size in (int(s) for s in args.sizes.split(",")):
                rows = store.setdefault(name, {}).setdefault(str(size), {})
                todo = subsets(len(ids), size, args.n, args.seed)
                if size == len(own):
                    todo = [("own", own)] + [(None, s) for s in todo]
                else:
                    todo = [(None, s) for s in todo]
                for tag, sub in todo:
                    key = tag or ",".join(ids[i] for i in sub)
                    if key in rows:
                        continue
                    rows[key] = run_subset(site, out, cfg, reference, {ids[i] for i in sub})
                    store_path.write_text(json.dumps(store, indent=1))
                    r = rows[key]
                    print(f"{name} {key}: " + (f"refused ({r['refused'][:120]})" if "refused" in r else
                          f"{r['aligned'][0]:.3f} m / {r['aligned'][1]:.1f} %" + (
                              f", check E/N/U {' / '.join(f'{x:.2f}' for x in r['check_enu'])}"
                              if r.get("check_enu") else "")) + f" ({r['seconds']:.0f} s)", flush=True)
            (out / "gcps.geojson").unlink(missing_ok=True)
    print_table(args.root, sites)
    return 0


if __name__ == "__main__":
    sys.exit(main())
