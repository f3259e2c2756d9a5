"""Accuracy of every correction beyond the paper, against the paper's plain path, on references
this project did not make. Prints one table; asserts nothing.

    python bench/bench_accuracy.py                         # every site found, every config
    python bench/bench_accuracy.py --sites omaha --configs paper,default --seeds 0,1,2
    python bench/bench_accuracy.py --table-only            # reprint the table from results.json

Configurations: `paper` (recon_core.config.BEYOND_PAPER switched off: the baseline), `default`
(what AE-Rec runs), `paper+NAME` (the paper with one correction on, with what it needs),
`default-NAME` (the defaults with one correction off) and `default+NAME` (the defaults with one
they leave off switched on). NAME is one of CORRECTIONS. Any of them followed by
`@section.key=VALUE` (repeatable) sets parameters too: `--configs default@mgm.p1=16` (a JSON
value, else a string; parameters of the sparse or dense stage get an OUT of their own).

Sites: `omaha` (../shared/data/omaha_3dates: an independent pushbroom simulator, 3 dates, a
ground-truth DSM), `gizeh` (d = 300), `reunion` (d = 400) (real Pleiades pairs, scored for agreement with
s2p's DSM: not ground truth), and synthetic presets of this project (`demo`, `tiny2`, ...,
generated under --root). A site that is absent is skipped with one line.

Figures per run: the fused DSM's median |error| and completeness (< 1 m) aligned and unaligned,
each date group's DSM alone (aligned median), check-point RMSE E / N / U (mean over groups).
Runs are kept under --root/<site>/sparse_<hash>[_s<seed>], one OUT per set of parameters up to
the upgrade (configurations that differ only from the upgrade on reuse its sparse and dense
stages), and the figures in --root/results.json.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recon_core.config import BEYOND_PAPER, Config, preset  # noqa: E402

SHARED = ROOT.parent / "shared" / "data"
REAL = {"omaha": ("omaha_3dates", None, None),
        "gizeh": ("gizeh_pair", 300, "ref_dsm_s2p.tif"),
        "reunion": ("reunion_pair", 400, "ref_dsm_s2p.tif")}

# each correction: the keys it owns, what it needs switched on with it, and the value that
# switches it on when the defaults leave it off
CORRECTIONS = {
    "refine": (["features.refine_half_px"], [], {}),
    "joint": (["sfm.joint_groups"], [], {}),
    "tie": (["sfm.tie_sigma_px"], [], {"sfm.tie_sigma_px": 0.01}),
    "within": (["sfm.correction_rounds"], ["sfm.joint_groups"], {}),
    "bend": (["sfm.bend_step"], ["sfm.joint_groups", "sfm.correction_rounds"], {}),
    "views": (["upgrade.view_sigma_deg"], [], {}),
    "prior": (["upgrade.metric_prior_sigma_cos"], [], {"upgrade.metric_prior_sigma_cos": 2e-3}),
    "metric_bend": (["upgrade.metric_bend"], [], {}),
}


def _default(key: str):
    sec, name = key.split(".")
    return getattr(getattr(Config(), sec), name)


def overrides_for(name: str) -> dict:
    """The overrides of a configuration name (module docstring; `default+X`: the defaults with
    X switched on, for a correction they leave off; `NAME@section.key=VALUE@...`: NAME with
    parameters set, e.g. `default@mgm.p1=16`)."""
    if "@" in name:
        base, *sets = name.split("@")
        ov = overrides_for(base)
        for item in sets:
            key, _, text = item.partition("=")
            try:
                ov[key] = json.loads(text)
            except ValueError:
                ov[key] = text
        return ov
    if name == "default":
        return {}
    if name == "paper":
        return dict(BEYOND_PAPER)
    for sign in "+-":
        base, s, corr = name.partition(sign)
        if s and base in ("paper", "default") and corr in CORRECTIONS:
            break
    else:
        raise SystemExit(f"unknown configuration {name!r}")
    keys, needs, on = CORRECTIONS[corr]
    if sign == "-":
        return {k: BEYOND_PAPER[k] for k in keys}
    ov = dict(BEYOND_PAPER) if base == "paper" else {}
    for k in keys + needs:
        ov.pop(k, None)
        if k in on:
            ov[k] = on[k]
        elif _default(k) == BEYOND_PAPER.get(k):      # off by default: nothing to switch on
            raise SystemExit(f"{name}: {k} has no value that switches it on")
    return ov


def site_for(name: str, root: Path, seed: int):
    """(site folder, tile size or None, reference DSM or None), or None when absent."""
    if name in REAL:
        folder, tile, ref = REAL[name]
        site = SHARED / folder
        if not site.is_dir():
            return None
        return site, tile, (site / ref if ref else None)
    from recon_core.synthetic.generator import generate_site

    site = root / "sites" / f"{name}_s{seed}"
    if not (site / "site.json").exists():
        t0 = time.time()
        generate_site(site, preset=name, seed=seed)
        print(f"generated {name} in {time.time() - t0:.0f} s -> {site}", flush=True)
    return site, (300 if name.startswith("tiny") else None), None


def figures(report: dict, out: Path, reference: Path | None) -> dict:
    st = report["stages"]
    fig = {}
    ev = st.get("eval") or {}
    if reference is not None and (out / "dsm.tif").exists():
        from recon_core.evaluation.evaluate import evaluate_dsm

        cached = out / "eval_reference.json"
        if cached.exists() and cached.stat().st_mtime >= (out / "dsm.tif").stat().st_mtime:
            ev = json.loads(cached.read_text())
        else:
            ev = evaluate_dsm(out / "dsm.tif", reference, out / "eval_reference")
            cached.write_text(json.dumps({k: ev[k] for k in ("aligned", "unaligned")}))
    for k in ("aligned", "unaligned"):
        if k in ev:
            fig[k] = (ev[k]["median_abs_err_m"], ev[k]["completeness_pct"])
    fig["groups"] = {g: v["aligned"]["median_abs_err_m"] for g, v in sorted((ev.get("groups") or {}).items())
                     if "aligned" in v}
    rm = []
    for u in (st.get("upgrade") or {}).get("groups", {}).values():
        c = (u.get("stats") or {}).get("check") or {}
        if c.get("n"):
            rm.append((c["rmse_E_m"], c["rmse_N_m"], c["rmse_U_m"]))
    if rm:
        fig["check_enu"] = tuple(sum(v[i] for v in rm) / len(rm) for i in range(3))
    fig["seconds"] = sum(v.get("seconds", 0.0) for v in st.values() if isinstance(v, dict))
    return fig


def run_one(site_name: str, config: str, seed: int, root: Path) -> dict | None:
    from recon_core.events import EventBus
    from recon_core.pipeline import run

    found = site_for(site_name, root, 0)
    if found is None:
        print(f"{site_name}: absent, skipped", flush=True)
        return None
    site, tile, reference = found
    cfg = preset("default").with_overrides(overrides_for(config)).with_overrides({"seed": seed})
    if tile:
        cfg = cfg.with_overrides({"tiling.tile_size": tile})
    # configurations that differ only from the upgrade on share one OUT: the run resumes the
    # sparse and dense stages (their hashes match) and redoes the rest
    ov = overrides_for(config)
    early = sorted((k, v) for k, v in ov.items() if not k.startswith(("upgrade.", "dsm.")))
    tag = hashlib.sha1(repr(early).encode()).hexdigest()[:8]
    out = root / site_name / (f"sparse_{tag}" + (f"_s{seed}" if seed else ""))
    t0 = time.time()
    msgs = []
    state = run(site, out, cfg, bus=EventBus(lambda ev: msgs.append(ev)), resume=True)
    fig = figures(state.report, out, reference)
    fig["wall_s"] = time.time() - t0
    return fig


def fmt(v, spec=".3f"):
    return "-" if v is None else format(v, spec)


def print_table(results: dict, sites: list[str], configs: list[str]) -> None:
    for site in sites:
        rows = {k.split("|", 1)[1]: v for k, v in results.items() if k.split("|", 1)[0] == site}
        if not rows:
            continue
        print(f"\n## {site}")
        print("| config | ME / CP aligned | unaligned | groups alone (ME) | check RMSE E / N / U (m) |")
        print("|---|---|---|---|---|")
        order = [c for c in configs if any(r.split("_s")[0] == c for r in rows)] or sorted(rows)
        for c in order:
            runs = [v for r, v in sorted(rows.items()) if r == c or r.startswith(c + "_s")]
            for v in runs:
                a, u = v.get("aligned"), v.get("unaligned")
                grp = ", ".join(fmt(x) for x in v.get("groups", {}).values()) or "-"
                enu = " / ".join(fmt(x, ".2f") for x in v["check_enu"]) if v.get("check_enu") else "-"
                print(f"| {c}{'' if len(runs) == 1 else ' (seed ' + str(v.get('seed', 0)) + ')'} | "
                      f"{fmt(a and a[0])} m / {fmt(a and a[1], '.1f')} % | "
                      f"{fmt(u and u[0])} m / {fmt(u and u[1], '.1f')} % | {grp} | {enu} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sites", default="omaha,gizeh,reunion,demo")
    ap.add_argument("--configs", default="paper," + ",".join(f"paper+{c}" for c in CORRECTIONS)
                    + "," + ",".join(f"default-{c}" for c in CORRECTIONS) + ",default")
    ap.add_argument("--seeds", default="0", help="seeds of every random choice (the run-to-run spread)")
    ap.add_argument("--root", type=Path, default=Path("/tmp/aerec_accuracy"))
    ap.add_argument("--table-only", action="store_true")
    ap.add_argument("--rerun", action="store_true", help="run again what results.json already has")
    args = ap.parse_args(argv)
    sites, configs = args.sites.split(","), args.configs.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    args.root.mkdir(parents=True, exist_ok=True)
    store = args.root / "results.json"
    results = json.loads(store.read_text()) if store.exists() else {}
    if not args.table_only:
        for site in sites:
            for config in configs:
                for seed in seeds:
                    key = f"{site}|{config}" + (f"_s{seed}" if seed else "")
                    if key in results and not args.rerun:
                        continue
                    t0 = time.time()
                    fig = run_one(site, config, seed, args.root)
                    if fig is None:
                        break
                    fig["seed"] = seed
                    results[key] = fig
                    store.write_text(json.dumps(results, indent=1))
                    a = fig.get("aligned")
                    print(f"{key}: {fmt(a and a[0])} m / {fmt(a and a[1], '.1f')} % "
                          f"({time.time() - t0:.0f} s)", flush=True)
                else:
                    continue
                break
    print_table(results, sites, configs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
