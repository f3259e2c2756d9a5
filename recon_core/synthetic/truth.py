"""Evaluation against the truth of a synthetic site (tests and benchmarks only).

The pipeline never imports this module: it reads `SITE/truth/` (the physical pushbroom cameras
written by `synthetic.generate_site`), which a real site does not have.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon_core.geometry import affine
from recon_core.geometry.geodesy import LocalFrame


def intersect_rays(origins: np.ndarray, dirs: np.ndarray, pt: np.ndarray, n: int) -> np.ndarray:
    """Least-squares intersection of groups of rays: (k, 3) origins/unit dirs, pt (k,) group ids."""
    d = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    P = np.eye(3)[None] - d[:, :, None] * d[:, None, :]          # projectors orthogonal to rays
    A = np.zeros((n, 9))
    b = np.zeros((n, 3))
    Pf = P.reshape(-1, 9)
    Po = np.einsum("kij,kj->ki", P, origins)
    for c in range(9):
        A[:, c] = np.bincount(pt, Pf[:, c], minlength=n)
    for c in range(3):
        b[:, c] = np.bincount(pt, Po[:, c], minlength=n)
    return affine.solve3x3(A.reshape(n, 3, 3), b)


def has_truth_cameras(site_dir: str | Path, rpc_truth: bool = False) -> bool:
    """The site has true cameras for evaluation: this project's generator's (truth/cameras.json)
    or, with `rpc_truth` (a site of another simulator whose RPCs were fitted to its true
    cameras, such as omaha_3dates: never a real product's RPC), every image's RPC."""
    site_dir = Path(site_dir)
    if (site_dir / "truth" / "cameras.json").exists():
        return True
    return rpc_truth and bool(_rpc_rays(site_dir))


def _rpc_rays(site_dir: Path) -> dict:
    """name -> rays function (n, 2) pixels -> (origins, unit directions) ECEF from the image's
    RPC (two localisations at heights apart); {} unless every image has an RPC."""
    import rasterio

    from recon_core.geometry.geodesy import geodetic_to_ecef
    from recon_core.geometry.rpc import RPCModel

    out = {}
    for p in sorted((site_dir / "images").glob("*.tif")):
        with rasterio.open(p) as src:
            if src.rpcs is None:
                return {}
            rpc = RPCModel.from_rasterio(src.rpcs)

        def rays(xy, rpc=rpc):
            lo = geodetic_to_ecef(rpc.localize(xy, rpc.height_off - 0.5 * rpc.height_scale))
            hi = geodetic_to_ecef(rpc.localize(xy, rpc.height_off + 0.5 * rpc.height_scale))
            return hi, hi - lo
        out[p.name] = rays
    return out


def true_points_enu(site_dir: str | Path, frame: LocalFrame, img_names: list[str], obs_img: np.ndarray,
                    obs_pt: np.ndarray, obs_xy: np.ndarray, n: int) -> np.ndarray:
    """Triangulate observations (image index, point index, pixel) with the TRUE cameras -> ENU:
    the generator's (truth/cameras.json) or, without them, the images' RPCs (the caller has
    checked that they are true cameras: has_truth_cameras)."""
    site_dir = Path(site_dir)
    if (site_dir / "truth" / "cameras.json").exists():
        from recon_core.synthetic.generator import load_truth_cameras

        rays = {name: cam.ray for name, cam in load_truth_cameras(site_dir).items()}
    else:
        rays = _rpc_rays(site_dir)
    O = np.zeros((len(obs_pt), 3))
    D = np.zeros((len(obs_pt), 3))
    for k, name in enumerate(img_names):
        sel = obs_img == k
        if sel.any():
            O[sel], D[sel] = rays[name](obs_xy[sel])
    # work relative to the frame origin for conditioning
    X = intersect_rays(O - frame.origin_ecef, D, obs_pt, n) + frame.origin_ecef
    return frame.ecef_to_enu(X)


def sparse_vs_truth(site_dir: str | Path, model, frame: LocalFrame, views=None) -> dict:
    """Fit one 3D affine map from the sparse points to their true positions; residual figures.

    The true position of a point is triangulated by the true cameras from its observations in
    the model's images, or in `views`' images (a model of more images holding the same track
    ids: the merged joint model of the date groups, whose other views make the truth of a
    group's weak-baseline points well-conditioned)."""
    ids = model.point_ids()
    src = model if views is None else views
    idx = src.active_obs()
    o = src.obs
    idx = idx[np.isin(o.track[idx], ids)]
    # one observation per (track, image) is enough for the true triangulation
    key = np.unique(np.stack([o.track[idx], o.img[idx]], 1), axis=0, return_index=True)[1]
    idx = idx[key]
    remap = np.full(len(model.X), -1)
    remap[ids] = np.arange(len(ids))
    Xt = true_points_enu(site_dir, frame, src.images, o.img[idx], remap[o.track[idx]], o.xy[idx], len(ids))
    return affine_fit_report(model.X[ids], Xt)


def affine_fit_report(X: np.ndarray, Xt: np.ndarray) -> dict:
    """Best-fit 3D affine map X -> Xt (fitted here, in evaluation only) and its residuals."""
    ok = np.all(np.isfinite(X), 1) & np.all(np.isfinite(Xt), 1)
    A = affine.fit_affine_3d(X[ok], Xt[ok])
    r = affine.apply_affine_3d(A, X[ok]) - Xt[ok]
    return {"n": int(ok.sum()), "rms_m": float(np.sqrt(np.mean(np.sum(r ** 2, 1)))),
            "rms_xyz_m": np.sqrt(np.mean(r ** 2, 0)).tolist(),
            "median_abs_u_m": float(np.median(np.abs(r[:, 2]))),
            "p95_m": float(np.percentile(np.linalg.norm(r, axis=1), 95)), "A": A, "residuals": r,
            "truth": Xt[ok], "bend": bend_report(Xt[ok], r[:, 2])}


def bend_report(Xt: np.ndarray, du: np.ndarray, cell_m: float = 150.0) -> dict:
    """How much of the vertical residual a smooth surface over the site explains: RMS of the
    residual, of a fitted quadratic in (E, N) (a dome or a saddle), and what remains; and its
    local part, each point's residual minus the mean of its cell of cell_m (point noise, not a
    bend: a weak pair's points show there)."""
    e, n = Xt[:, 0] - Xt[:, 0].mean(), Xt[:, 1] - Xt[:, 1].mean()
    s = max(np.ptp(e), np.ptp(n), 1e-9)
    e, n = e / s, n / s
    A = np.column_stack([np.ones_like(e), e, n, e * e, e * n, n * n])
    coef = np.linalg.lstsq(A, du, rcond=None)[0]
    fit = A @ coef
    _, cell = np.unique(np.floor(Xt[:, :2] / cell_m).astype(np.int64), axis=0, return_inverse=True)
    cell = cell.ravel()
    local = du - (np.bincount(cell, du) / np.bincount(cell))[cell]
    return {"rms_u_m": float(np.sqrt(np.mean(du ** 2))), "quadratic_rms_m": float(np.sqrt(np.mean(fit ** 2))),
            "rest_rms_m": float(np.sqrt(np.mean((du - fit) ** 2))),
            "quadratic_range_m": float(np.ptp(fit)), "local_rms_m": float(np.sqrt(np.mean(local ** 2)))}


def residual_map(Xt: np.ndarray, du: np.ndarray, cell_m: float = 50.0, clip_m: float = 1.0) -> np.ndarray:
    """RGB map of the mean vertical residual per cell of cell_m over the site (north up),
    diverging colours clipped at +-clip_m, with a colour bar; grey where no point."""
    from recon_core.evaluation import colormap as cm

    e0, n1 = Xt[:, 0].min(), Xt[:, 1].max()
    col = ((Xt[:, 0] - e0) // cell_m).astype(int)
    row = ((n1 - Xt[:, 1]) // cell_m).astype(int)
    h, w = row.max() + 1, col.max() + 1
    s = np.bincount(row * w + col, du, minlength=h * w)
    c = np.bincount(row * w + col, minlength=h * w)
    m = np.where(c > 0, s / np.maximum(c, 1), np.nan).reshape(h, w)
    rgb = cm.diverging(m, clip_m)
    rgb[~np.isfinite(m)] = 160
    rgb = cm.resize_for_display(rgb, 300, 900)
    bar = cm.colorbar(rgb.shape[0], -clip_m, clip_m, lambda v: cm.diverging(v, clip_m))
    return cm.hstack([rgb, bar])
