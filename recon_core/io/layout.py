"""Every path under OUT, in one object used by the core and the viewer alike.

    OUT/
      report.json                      per-stage summaries of the run that wrote these files
      gcps.geojson                     the working GCP set (the viewer's edits), when present
      stages/<stage>.json              what makes a stage resumable (hash of its inputs)
      affine/group_<k>/cameras.json    tiles, registration flags, 2 x 4 tile cameras
      affine/group_<k>/sparse.ply      sparse points in the group's affine frame
      affine/group_<k>/observations.npz  every tile observation, point ids
      affine/group_<k>/dense.ply       dense points in the group's affine frame
      upgrade/group_<k>.json           H_A of group k and its GCP report
      upgrade/frame.json               the local ENU frame shared by all groups
      cloud.ply                        the Euclidean cloud (output CRS, ellipsoidal h)
      cloud.laz                        the same as LAS 1.4 with its CRS (dsm.laz)
      dsm.tif                          the DSM (date groups fused)
      dsm_groups/group_<k>.tif         each date group's own DSM, when there are several
      dsm_agreement.tif                per cell of dsm.tif, how many date groups agree on its
                                       height (0: a weak pair's or a filled small hole), when
                                       there are several
      eval/                            eval.json, height_error.tif/.png, dsm_vs_gt.png
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import overload


class _At:
    """A file or folder at a fixed place under OUT (the path relative to it)."""

    def __init__(self, rel: str):
        self.rel = rel

    @overload
    def __get__(self, layout: None, owner=None) -> _At: ...
    @overload
    def __get__(self, layout: OutLayout, owner=None) -> Path: ...

    def __get__(self, layout: OutLayout | None, owner=None) -> Path | _At:
        return self if layout is None else layout.root / self.rel


class _Each:
    """A file or folder per group or per stage: `rel` names it with `{}` for the group number or
    the stage name; reading the attribute gives the function of that value."""

    def __init__(self, rel: str):
        self.rel = rel

    @overload
    def __get__(self, layout: None, owner=None) -> _Each: ...
    @overload
    def __get__(self, layout: OutLayout, owner=None) -> Callable[[int | str], Path]: ...

    def __get__(self, layout: OutLayout | None, owner=None) -> Callable[[int | str], Path] | _Each:
        if layout is None:
            return self
        return lambda key: layout.root / self.rel.format(key)


@dataclass(frozen=True)
class OutLayout:
    """The files of one output folder (nothing is created or read by building it)."""

    root: Path

    def __init__(self, root: str | Path):
        object.__setattr__(self, "root", Path(root))

    # the run
    report = _At("report.json")
    gcps = _At("gcps.geojson")             # the working GCP set (the viewer's edits; the run uses
                                            # it when it exists)
    stage_record = _Each("stages/{}.json")

    # affine models
    group_dir = _Each("affine/group_{}")
    cameras = _Each("affine/group_{}/cameras.json")
    sparse_ply = _Each("affine/group_{}/sparse.ply")
    observations = _Each("affine/group_{}/observations.npz")
    dense_ply = _Each("affine/group_{}/dense.ply")

    # Euclidean products
    upgrade_record = _Each("upgrade/group_{}.json")
    upgrade_frame = _At("upgrade/frame.json")
    cloud = _At("cloud.ply")
    cloud_laz = _At("cloud.laz")
    dsm = _At("dsm.tif")
    dsm_agreement = _At("dsm_agreement.tif")   # per cell of the fused DSM, how many date groups
                                                # agree on its height
    group_dsm = _Each("dsm_groups/group_{}.tif")   # one date group's own DSM (when several)

    # evaluation
    eval_dir = _At("eval")
    eval_json = _At("eval/eval.json")
    height_error_tif = _At("eval/height_error.tif")
    height_error_png = _At("eval/height_error.png")
    dsm_vs_gt_png = _At("eval/dsm_vs_gt.png")

    # which groups have products
    def model_groups(self) -> list[int]:
        """Groups with a saved sparse model, ascending."""
        return _indices(self.root / "affine", r"group_(\d+)", lambda p: (p / "cameras.json").exists())

    def upgraded_groups(self) -> list[int]:
        return _indices(self.root / "upgrade", r"group_(\d+)\.json", lambda p: p.is_file())

    def group_dsms(self) -> list[int]:
        return _indices(self.root / "dsm_groups", r"group_(\d+)\.tif", lambda p: p.is_file())

    def stage_products(self, stage: str) -> list[Path]:
        """The files and folders a stage writes (those that exist), beside its record."""
        if stage == "sparse":
            found = [p for g in self.model_groups() for p in (self.cameras(g), self.sparse_ply(g),
                                                             self.observations(g))]
        elif stage == "dense":
            found = [self.dense_ply(g) for g in self.model_groups()]
        elif stage == "upgrade":
            found = [self.root / "upgrade"]
        elif stage == "dsm":
            found = [self.dsm, self.root / "dsm_groups", self.dsm_agreement, self.cloud, self.cloud_laz]
        elif stage == "eval":
            found = [self.eval_dir]
        else:
            raise ValueError(f"unknown stage {stage!r}")
        return [p for p in found if p.exists()]

    def scratch(self) -> list[Path]:
        """Scratch left by an interrupted run: atomic-write temporaries (.NAME.XXXXXXXX.SUFFIX, and
        GDAL's .ovr.tmp of one), dense job parts (.dense_parts_*), spilled DSM blocks
        (dsm_blocks_*), the DSM stage's grids on disk (.dsm_work_*) and the sparse stage's
        spilled descriptors (.sparse_desc_*), down to the group
        folders. (One run per output folder at a time.)"""
        found = []
        for d in [self.root, self.root / "stages", self.root / "upgrade", self.root / "eval",
                  self.root / "dsm_groups", self.root / "affine",
                  *[self.group_dir(g) for g in _indices(self.root / "affine", r"group_(\d+)", Path.is_dir)]]:
            if d.is_dir():
                found += [p for p in d.iterdir() if _SCRATCH.fullmatch(p.name)]
        return sorted(found)

    def is_output(self) -> bool:
        """Does the folder look like a (possibly partial) output folder?"""
        return self.report.exists() or (self.root / "affine").is_dir()


_SCRATCH = re.compile(r"\.[^/]+\.[A-Za-z0-9_]{8}\.[A-Za-z0-9]+(\.ovr\.tmp)?|\.dense_parts_[A-Za-z0-9_]+|\.dsm_work_[A-Za-z0-9_]+|\.sparse_desc_[A-Za-z0-9_]+|dsm_blocks_[A-Za-z0-9_]+")


def _indices(folder: Path, pattern: str, keep) -> list[int]:
    if not folder.is_dir():
        return []
    out = []
    for p in folder.iterdir():
        m = re.fullmatch(pattern, p.name)
        if m and keep(p):
            out.append(int(m.group(1)))
    return sorted(out)
