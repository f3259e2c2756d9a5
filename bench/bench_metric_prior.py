"""The upgrade with and without the cameras' metric constraint, on a finished run.

    python bench/bench_metric_prior.py OUT SITE [--sigma 0 0.001 0.002 0.005]

For each sigma_cos (0 = GCPs only) it refits H_A on the run's models and GCPs (the merged model
of a joint run, else each group) and prints the check points' RMSE E / N / U, the control
points' vertical RMS and the per-image row cosines; on a synthetic site (SITE/truth) also the
height scale and shears of H_A against the truth (H_A times the inverse of the sparse
structure's best affine map to the true points: 1 and 0 when exact).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from recon_core.euclidean.georef import upgrade_group
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.gcps import read_gcps_geojson, working_gcp_file
from recon_core.io.models import load_model
from recon_core.model.sparse_model import merge_joint


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("site", type=Path)
    ap.add_argument("--sigma", type=float, nargs="+", default=[0.0, 1e-3, 2e-3, 5e-3])
    args = ap.parse_args()
    rep = json.loads((args.out / "report.json").read_text())
    frame = LocalFrame(**rep["stages"]["upgrade"]["frame"])
    groups = sorted(int(g) for g in rep["stages"]["sparse"]["groups"])
    models = [load_model(args.out, g) for g in groups]
    joint = merge_joint(models) if len(models) > 1 else None
    todo = [joint] if joint is not None else models
    gcps = read_gcps_geojson(working_gcp_file(args.site, args.out))
    truth = (args.site / "truth").is_dir()
    for m in todo:
        label = "joint model" if m is joint else f"group {m.group}"
        print(f"{label}: {len(m.images)} images, {int(m.registered.sum())} tiles")
        A_true = None
        if truth:
            from recon_core.synthetic.truth import sparse_vs_truth
            A_true = sparse_vs_truth(args.site, m, frame)["A"]
        for s in args.sigma:
            res, _, _ = upgrade_group(m, gcps, frame, sigma_cos=s)
            chk = res.stats.get("check") or {}
            ctrl_u = [p["dU"] for p in res.points if p["status"] == "used"]
            line = (f"  sigma_cos {s:<6g} check RMSE E/N/U "
                    f"{chk.get('rmse_E_m', float('nan')):.3f} / {chk.get('rmse_N_m', float('nan')):.3f} / "
                    f"{chk.get('rmse_U_m', float('nan')):.3f} m (n {chk.get('n', 0)}), control RMS U "
                    f"{np.sqrt(np.mean(np.square(ctrl_u))):.3f} m, expected height error "
                    f"{res.conditioning.get('expected_height_error_m', float('nan')):.2f} m")
            if A_true is not None:
                D = res.H[:3, :3] @ np.linalg.inv(A_true[:3, :3])
                line += f"; vs truth: height scale {D[2, 2]:.4f}, shear E {D[0, 2]:+.4f} N {D[1, 2]:+.4f}"
            print(line)
            mp = res.metric_prior
            if mp:
                cos = np.array(list(mp["row_cosine"].values())) * 1e3
                print(f"    row cosines x1e3 {np.round(cos, 2).tolist()}, height of a "
                      f"{mp['at_height_m']:g} m structure moved {mp['height_change_m']:+.3f} m")


if __name__ == "__main__":
    main()
