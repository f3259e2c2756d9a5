"""The images' lines of sight and the height scale, against the images' own RPCs (for evaluation
only: the pipeline never reads them). Prints figures; asserts nothing.

    python bench/bench_sight.py SITE OUT [--subsets 200]

SITE: a site whose images carry RPCs and whose sidecars state their viewing direction ("view";
bench/bench_gcp_subsets.py makes such sites from the shared data); OUT: a finished run on it
(sparse at least). The truth here is the true local affine camera of every registered tile, the
RPC's Jacobian at the tile's centre and the GCPs' mean height, in the run's ENU frame: the
one 3 x 3 map A that best carries the truth's tile cameras onto the run's (M_run = M_true A)
is the affine frame's true linear part. Printed:

- per image: the vendor's direction against the RPC's line of sight at the image centre; the
  run's tile lines of sight (null vectors of the tile cameras) through A against the RPC's
  (median and largest angle); the cosine between the rows of the true tile cameras in metres
  (what the metric prior assumes to be 0);
- the height scale and the lean of heights (H_A A^-1: 1 and 0 when exact) of the GCPs-only fit
  and of the fit held by the images, for the site's own control set and for random 4-GCP
  subsets (median and 90th percentile of |scale - 1|);
- per GCP: where the images' own RPCs put its image observations (triangulated) against its
  surveyed position, in ENU, with the common offset removed: a GCP whose survey and clicks
  disagree under the true cameras limits every control set it is in, whatever the upgrade does.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from dataclasses import replace
from itertools import combinations
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon_core.config import Config  # noqa: E402
from recon_core.euclidean.georef import frame_for, upgrade_group  # noqa: E402
from recon_core.euclidean.sight import lines_of_sight, tile_sight  # noqa: E402
from recon_core.io.models import load_model  # noqa: E402
from recon_core.io.site import load_site  # noqa: E402
from recon_core.model.sparse_model import merge_joint  # noqa: E402


def true_tile_cameras(site, model, frame, h_enu: float) -> tuple[np.ndarray, np.ndarray]:
    """(T, 2, 3) the RPC's Jacobian (px per ENU metre) at each registered tile's centre, and the
    tile indices."""
    import rasterio
    from rasterio.transform import RPCTransformer

    h = float(frame.enu_to_geodetic(np.array([[0.0, 0.0, h_enu]]))[0, 2])
    trs, out, idx = {}, [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for t in np.flatnonzero(model.registered):
            tile = model.tiles[t]
            if tile.image not in trs:
                with rasterio.open(site.image(tile.image).path) as ds:
                    trs[tile.image] = RPCTransformer(ds.rpcs)
            tr = trs[tile.image]
            lon, lat = tr.xy(tile.row0 + tile.height / 2, tile.col0 + tile.width / 2, zs=h)
            Y0 = frame.geodetic_to_enu(np.array([[lon, lat, h]]))[0]

            def proj(Y):
                llh = frame.enu_to_geodetic(Y[None])[0]
                r, c = tr.rowcol(llh[0], llh[1], zs=llh[2], op=lambda x: x)
                return np.array([c, r], dtype=np.float64)
            J = np.zeros((2, 3))
            for a in range(3):
                d = np.zeros(3)
                d[a] = 5.0
                J[:, a] = (proj(Y0 + d) - proj(Y0 - d)) / 10.0
            out.append(J)
            idx.append(t)
    return np.array(out), np.array(idx)


def camera_truth(M_true: np.ndarray, M_run: np.ndarray) -> np.ndarray:
    """The 3 x 3 A with M_run ~ M_true A over every tile (least squares)."""
    rows, rhs = [], []
    for Mt, Mr in zip(M_true, M_run):
        for i in range(2):
            for j in range(3):
                row = np.zeros(9)
                row[3 * np.arange(3) + j] = Mt[i]
                rows.append(row)
                rhs.append(Mr[i, j])
    return np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0].reshape(3, 3)


def gcps_against_rpcs(site, frame) -> list[tuple[str, np.ndarray, float]]:
    """(id, triangulated - surveyed ENU (3,), reprojection RMS px) per GCP with >= 2 observations:
    its image observations intersected through the images' RPCs."""
    import rasterio
    from rasterio.transform import RPCTransformer
    from scipy.optimize import least_squares

    trs, out = {}, []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for g in site.gcps:
            if len(g.observations) < 2:
                continue
            for name in g.observations:
                if name not in trs:
                    with rasterio.open(site.image(name).path) as ds:
                        trs[name] = RPCTransformer(ds.rpcs)
            Y0 = frame.geodetic_to_enu(np.array([[g.lon, g.lat, g.h]]))[0]

            def resid(Y, g=g):
                llh = frame.enu_to_geodetic(Y[None])[0]
                r = []
                for name, (c, rw) in g.observations.items():
                    rr, cc = trs[name].rowcol([llh[0]], [llh[1]], zs=[llh[2]], op=lambda x: x)
                    r += [cc[0] - c, rr[0] - rw]
                return np.array(r)
            sol = least_squares(resid, Y0)
            out.append((g.id, sol.x - Y0, float(np.sqrt(np.mean(sol.fun ** 2)))))
    return out


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    return float(np.degrees(np.arccos(min(1.0, abs(float(u @ v)) / np.linalg.norm(u) / np.linalg.norm(v)))))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("site", type=Path)
    ap.add_argument("out", type=Path)
    ap.add_argument("--subsets", type=int, default=200)
    args = ap.parse_args(argv)
    site = load_site(args.site)
    rep = json.loads((args.out / "report.json").read_text())
    models = [load_model(args.out, int(g)) for g in rep["stages"]["sparse"]["groups"]]
    model = merge_joint(models) if len(models) > 1 else models[0]
    model = model or models[0]
    frame = frame_for(site.gcps)
    images = {im.name: im for im in site.images}
    h_enu = float(np.mean(frame.geodetic_to_enu(np.array([g.llh for g in site.gcps]))[:, 2]))
    M_true, tiles = true_tile_cameras(site, model, frame, h_enu)
    M_run = np.array([model.cams[t][:, :3] for t in tiles])
    A = camera_truth(M_true, M_run)
    resid = M_run - M_true @ A
    print(f"{site.name}: {len(tiles)} tiles; the run's tile cameras against the truth's through one "
          f"affine map: {100 * np.sqrt(np.mean(resid ** 2) / np.mean(M_run ** 2)):.2f} % RMS")
    rays = {r.image: r for r in lines_of_sight(model, images)}
    print("| image | vendor view vs RPC sight at the centre (deg) | tile sights vs truth: median / max (deg) "
          "| true row cosine (median) |")
    print("|---|---|---|---|")
    for name in model.images:
        k = [i for i, t in enumerate(tiles) if model.tiles[t].image == name]
        tile_ang = [angle_deg(A @ tile_sight(M_run[i]), tile_sight(M_true[i])) for i in k]
        cos = [float(M_true[i][0] @ M_true[i][1] / np.linalg.norm(M_true[i][0]) / np.linalg.norm(M_true[i][1]))
               for i in k]
        centre = min(k, key=lambda i: np.hypot(
            model.tiles[tiles[i]].col0 + model.tiles[tiles[i]].width / 2 - images[name].width / 2,
            model.tiles[tiles[i]].row0 + model.tiles[tiles[i]].height / 2 - images[name].height / 2))
        vend = "-" if name not in rays else f"{angle_deg(rays[name].v_local, tile_sight(M_true[centre])):.3f}"
        print(f"| {name} | {vend} | {np.median(tile_ang):.3f} / {np.max(tile_ang):.3f} | {np.median(cos):+.1e} |")

    def shape(H):
        D = H[:3, :3] @ np.linalg.inv(A)
        return D[2, 2], D[0, 2], D[1, 2]

    def fit(gcps, held):
        res, _, _ = upgrade_group(model, gcps, frame, images=images if held else None,
                                  sigma_view_deg=Config().upgrade.view_sigma_deg)
        return res.H

    print("\n| control set | fit | height scale | lean E / N (per m of height) |")
    print("|---|---|---|---|")
    for held in (False, True):
        s = shape(fit(site.gcps, held))
        print(f"| the site's own | {'held by the images' if held else 'GCPs alone'} | {s[0]:.4f} | "
              f"{s[1]:+.4f} / {s[2]:+.4f} |")
    rng = np.random.default_rng(0)
    allc = list(combinations(range(len(site.gcps)), 4))
    pick = [allc[i] for i in rng.choice(len(allc), min(args.subsets, len(allc)), replace=False)]
    errs = {False: [], True: []}
    for q in pick:
        gcps = [replace(g, role="control" if k in q else "check") for k, g in enumerate(site.gcps)]
        for held in (False, True):
            try:
                errs[held].append(abs(shape(fit(gcps, held))[0] - 1.0))
            except Exception:                       # a degenerate set the GCPs alone cannot fit
                errs[held].append(np.inf)
    for held in (False, True):
        e = np.array(errs[held])
        print(f"| {len(pick)} random 4-subsets | {'held by the images' if held else 'GCPs alone'} | "
              f"|scale - 1| median {np.median(e):.4f}, 90th percentile {np.percentile(e, 90):.4f} | "
              f"{int(np.sum(~np.isfinite(e)))} not fitted |")
    rows = gcps_against_rpcs(site, frame)
    if rows:
        d = np.array([r[1] for r in rows])
        off = np.median(d, axis=0)
        print(f"\nThe GCPs' image observations intersected through the RPCs, minus their surveyed position "
              f"(common offset E / N / U {off[0]:+.3f} / {off[1]:+.3f} / {off[2]:+.3f} m removed):")
        print("| GCP | dE | dN | dU (m) | reprojection RMS (px) |")
        print("|---|---|---|---|---|")
        for (gid, dv, px) in rows:
            e = dv - off
            print(f"| {gid} | {e[0]:+.3f} | {e[1]:+.3f} | {e[2]:+.3f} | {px:.2f} |")
        r = d - off
        print(f"| RMS | {np.sqrt(np.mean(r[:, 0] ** 2)):.3f} | {np.sqrt(np.mean(r[:, 1] ** 2)):.3f} | "
              f"{np.sqrt(np.mean(r[:, 2] ** 2)):.3f} | |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
