"""The files of the reconstruction's models under OUT (paths: recon_core.io.layout.OutLayout).

  affine/group_<k>/cameras.json     tiles (offset, size), registration flag, 2 x 4 camera, gauge
  affine/group_<k>/sparse.ply       points (affine frame, float64), grey colour, views, error
  affine/group_<k>/observations.npz every (tile, track) observation: tile, track, xy, img, valid;
                                    point_ids = track id of each sparse.ply vertex, in order
  affine/group_<k>/dense.ply        dense points (affine frame), grey, n_views, reproj_px, weak
  upgrade/group_<k>.json            H_A (affine -> local ENU) and the group's GCP report
  upgrade/frame.json                the local ENU frame (origin lon, lat, h)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from recon_core.geometry.enu_map import EnuMap
from recon_core.geometry.geodesy import LocalFrame
from recon_core.io.files import atomic_path, write_json
from recon_core.io.layout import OutLayout
from recon_core.io.ply import PlyWriter, open_ply, ply_fields, read_ply, write_ply
from recon_core.model.dense_cloud import DenseCloud
from recon_core.model.sparse_model import Observations, SparseModel
from recon_core.model.tiling import Tile


def as_layout(out: OutLayout | str | Path) -> OutLayout:
    return out if isinstance(out, OutLayout) else OutLayout(out)


# -- sparse models ------------------------------------------------------------------------------
def save_model(model: SparseModel, out: OutLayout | str | Path) -> Path:
    """Write affine/group_<k>/{cameras.json, sparse.ply, observations.npz} (atomically each)."""
    lay = as_layout(out)
    d = lay.group_dir(model.group)
    d.mkdir(parents=True, exist_ok=True)
    doc = {"group": model.group, "images": model.images,
           "frame": "affine; gauge = canonical frame of the initial tile pair "
                    "(first camera [I2|0|0], one row of the second camera [0 0 1|0])"
                    + ("; shared by every date group of a joint reconstruction (stats.joint)"
                       if "joint" in model.stats else ""),
           "camera_convention": "x = P @ [X, Y, Z, 1]: full-image pixel (col, row), centre of the "
                                "top-left pixel at (0, 0)",
           "init_tiles": [model.tiles[t].id if t >= 0 else None for t in model.init_tiles],
           "register_order": [model.tiles[t].id for t in model.register_order],
           "tiles": [dict(t.to_dict(), registered=bool(model.registered[k]),
                          camera=model.cams[k].tolist(), fixed=model.fixed[k].tolist())
                     for k, t in enumerate(model.tiles)],
           "stats": model.stats}
    write_json(lay.cameras(model.group), doc)
    ids, nimg, rms = model.point_stats()
    g = model.gray[ids]
    write_ply(lay.sparse_ply(model.group), model.X[ids], np.stack([g, g, g], 1),
              {"n_views": nimg.astype(np.float32),
               "reproj_px": rms.astype(np.float32)}, comments=affine_frame_comments(model.group))
    o = model.obs
    with atomic_path(lay.observations(model.group)) as tmp:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, tile=o.tile, track=o.track, xy=o.xy, img=o.img, valid=o.valid,
                                corr=o.correction, gray=model.gray, point_ids=ids)
    return d


def load_model(out: OutLayout | str | Path, g: int) -> SparseModel:
    """The sparse model of group g as save_model wrote it."""
    lay = as_layout(out)
    doc = json.loads(lay.cameras(g).read_text())
    tiles = [Tile.from_dict(t) for t in doc["tiles"]]
    cams = np.array([t["camera"] for t in doc["tiles"]], dtype=np.float64).reshape(-1, 2, 4)
    fixed = np.array([t["fixed"] for t in doc["tiles"]], dtype=bool).reshape(-1, 2, 4)
    reg = np.array([t["registered"] for t in doc["tiles"]], dtype=bool)
    z = np.load(lay.observations(g))
    obs = Observations(z["tile"], z["track"], z["xy"], z["img"], z["valid"],
                       z["corr"].astype(np.float64) if "corr" in z.files else None)
    gray = z["gray"]
    xyz, _, _ = read_ply(lay.sparse_ply(g))
    ids = z["point_ids"].astype(np.int64)
    X = np.zeros((len(gray), 3))
    X[ids] = xyz
    has = np.zeros(len(gray), bool)
    has[ids] = True
    index = {t.id: k for k, t in enumerate(tiles)}
    m = SparseModel(doc["group"], doc["images"], tiles, cams, reg, fixed, obs, X, has, gray,
                    [index[i] for i in doc["register_order"]],
                    tuple(index.get(i, -1) if i is not None else -1 for i in doc["init_tiles"]),
                    doc.get("stats", {}))
    return m


# -- dense clouds -------------------------------------------------------------------------------
DENSE_EXTRA = ("n_views", "reproj_px", "weak")


def affine_frame_comments(group: int) -> list[str]:
    """PLY header comments of a cloud in a group's affine frame."""
    return [f"frame affine reconstruction of date group {group}: defined up to a 3D affine map, not metres",
            f"frame upgrade/group_{group}.json (H, 4 x 4) maps x y z to the local ENU frame of "
            "upgrade/frame.json (metres, WGS84 ellipsoidal heights)"]


def dense_writer(path: Path, group: int | None = None) -> PlyWriter:
    """The streaming writer of a dense.ply (x y z float64, grey as RGB, n_views, reproj_px,
    weak: 1 for a two-view point of a weak pair)."""
    return PlyWriter(path, list(DENSE_EXTRA), with_colors=True,
                     comments=() if group is None else affine_frame_comments(group))


def load_dense(out: OutLayout | str | Path, g: int) -> DenseCloud | None:
    """The whole dense cloud of a group in memory (small sites; large ones: PointSource)."""
    path = as_layout(out).dense_ply(g)
    if not path.exists():
        return None
    xyz, rgb, extra = ply_fields(open_ply(path))
    assert rgb is not None                       # the dense stage writes colours
    return DenseCloud(xyz, rgb[:, 0].copy(), extra["n_views"].astype(np.uint8), extra["reproj_px"],
                      extra["weak"] > 0 if "weak" in extra else None)


class PointSource:
    """A group's affine cloud, read by slices: a memory-mapped PLY on disk, or arrays."""

    def __init__(self, xyz: np.ndarray | None = None, gray: np.ndarray | None = None,
                 ply: Path | None = None):
        self._rec = open_ply(ply) if ply is not None else None
        self._xyz, self._gray = xyz, gray

    def __len__(self) -> int:
        if self._rec is not None:
            return len(self._rec)
        assert self._xyz is not None             # arrays when no PLY
        return len(self._xyz)

    def read(self, a: int, b: int, step: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """(xyz (k, 3) float64, grey (k,) uint8) of points a, a + step, ... < b."""
        if self._rec is None:
            assert self._xyz is not None and self._gray is not None   # arrays when no PLY
            return np.asarray(self._xyz[a:b:step], np.float64), np.asarray(self._gray[a:b:step], np.uint8)
        xyz, rgb, _ = ply_fields(self._rec[a:b:step])
        return xyz, (rgb[:, 0] if rgb is not None else np.full(len(xyz), 128, np.uint8))

    def tier(self, a: int, b: int) -> np.ndarray | None:
        """(k,) uint8 DSM tier of points a..b (1: a weak pair's two-view point, a fallback), or
        None when the cloud has no such marks (arrays, an older dense.ply: every point counts
        alike)."""
        if self._rec is None or "weak" not in (self._rec.dtype.names or ()):
            return None
        return (np.asarray(self._rec["weak"][a:b]) > 0).astype(np.uint8)

    def sample(self, max_n: int) -> np.ndarray:
        """At most max_n points spread evenly through the cloud (every k-th)."""
        return self.read(0, len(self), max(1, -(-len(self) // max_n)))[0]


# -- upgrade records ------------------------------------------------------------------------------
def save_upgrade(out: OutLayout | str | Path, records: dict[int, dict], frame: LocalFrame) -> None:
    """upgrade/group_<k>.json for each upgraded group and upgrade/frame.json; records of groups
    not upgraded this time are removed, so the folder always describes one upgrade."""
    lay = as_layout(out)
    for g in lay.upgraded_groups():
        if g not in records:
            lay.upgrade_record(g).unlink()
    for g, rec in sorted(records.items()):
        write_json(lay.upgrade_record(g), rec)
    write_json(lay.upgrade_frame, frame.to_dict())


def load_upgrade(out: OutLayout | str | Path) -> tuple[dict, LocalFrame] | None:
    """({group: EnuMap (H_A and the metric bend step's warp)}, frame) as save_upgrade wrote
    them; None before any upgrade."""
    lay = as_layout(out)
    if not lay.upgrade_frame.exists():
        return None
    fr = json.loads(lay.upgrade_frame.read_text())
    frame = LocalFrame(fr["lon0"], fr["lat0"], fr["h0"])
    maps = {g: EnuMap.from_record(json.loads(lay.upgrade_record(g).read_text())) for g in lay.upgraded_groups()}
    return maps, frame
