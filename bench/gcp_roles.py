"""Write a run's working GCP set (OUT/gcps.geojson) with other control / check roles, as a user
with more surveyed points, or who avoids one, would; prints the choice, asserts nothing.

    python bench/gcp_roles.py SITE OUT --control 4 --min-views 3
    python bench/gcp_roles.py SITE OUT --control 12

Control GCPs are chosen among those observed in at least --min-views images: the 4 spread in
plan and height that the synthetic generator picks (recon_core.synthetic.generator.
control_quadruple), then the point farthest in plan from those chosen, until --control. The
others become check points. Only the site's GCP file is read (ids, coordinates, observations),
never its truth. `--restore` removes OUT/gcps.geojson (the run then reads the site's file).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.geometry.geodesy import LocalFrame  # noqa: E402
from recon_core.synthetic.generator import control_quadruple  # noqa: E402


def choose(features: list[dict], n_control: int, min_views: int) -> list[int]:
    llh = np.array([f["geometry"]["coordinates"] for f in features], dtype=np.float64)
    frame = LocalFrame(*llh.mean(0))
    xyh = frame.geodetic_to_enu(llh)
    cand = [k for k, f in enumerate(features) if len(f["properties"]["observations"]) >= min_views]
    if len(cand) < max(4, n_control):
        raise SystemExit(f"only {len(cand)} GCPs observed in >= {min_views} images")
    chosen = [cand[i] for i in sorted(control_quadruple(xyh[cand]))]
    while len(chosen) < n_control:
        rest = [k for k in cand if k not in chosen]
        d = np.min(np.linalg.norm(xyh[rest][:, None, :2] - xyh[chosen][None, :, :2], axis=2), axis=1)
        chosen.append(rest[int(np.argmax(d))])
    return chosen


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("site", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--control", type=int, default=4)
    ap.add_argument("--min-views", type=int, default=2)
    ap.add_argument("--restore", action="store_true")
    args = ap.parse_args()
    target = args.out / "gcps.geojson"
    if args.restore:
        target.unlink(missing_ok=True)
        print(f"removed {target}: runs read {args.site / 'gcps.geojson'}")
        return 0
    doc = json.loads((args.site / "gcps.geojson").read_text())
    feats = doc["features"]
    chosen = set(choose(feats, args.control, args.min_views))
    for k, f in enumerate(feats):
        f["properties"]["role"] = "control" if k in chosen else "check"
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = target.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc, indent=1))
    tmp.replace(target)
    ids = [f["properties"]["id"] for k, f in enumerate(feats) if k in chosen]
    print(f"{target}: {len(ids)} control ({', '.join(ids)}), {len(feats) - len(ids)} check")
    return 0


if __name__ == "__main__":
    sys.exit(main())
