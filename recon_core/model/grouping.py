"""Date groups: images taken less than `max_gap_days` apart are processed together."""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime

from recon_core.errors import InputError
from recon_core.model.images import ImageInfo, iso_utc


def _acquired(im: ImageInfo) -> datetime:
    """An image's acquisition time (grouping by date needs one: group_by_date checks)."""
    assert im.acquired is not None
    return im.acquired


@dataclass
class Group:
    """One date group: its index and images in time order."""

    index: int
    images: list[ImageInfo]

    @property
    def span_days(self) -> float:
        return (_acquired(self.images[-1]) - _acquired(self.images[0])).total_seconds() / 86400.0

    def describe(self) -> str:
        a, b = _acquired(self.images[0]), _acquired(self.images[-1])
        return (f"group {self.index}: {len(self.images)} image(s), {iso_utc(a)[:10]} .. "
                f"{iso_utc(b)[:10]} (span {self.span_days:.1f} d)")


def group_by_date(images: list[ImageInfo], max_gap_days: float = 15.0,
                  max_span_days: float | None = 30.0) -> list[Group]:
    """Chain images sorted by time; split where the gap is >= max_gap_days.

    Chaining alone can make one group span months when acquisitions are regular, so a group is
    also closed once adding the next image would make it span more than `max_span_days`
    (None disables the cap).
    """
    for im in images:
        if im.acquired is None:
            raise InputError(im.path, "no acquisition time: cannot group by date")
    ordered = sorted(images, key=lambda im: (im.acquired, im.name))
    groups: list[list[ImageInfo]] = []
    for im in ordered:
        if groups:
            cur = groups[-1]
            gap = (_acquired(im) - _acquired(cur[-1])).total_seconds() / 86400.0
            span = (_acquired(im) - _acquired(cur[0])).total_seconds() / 86400.0
            if gap < max_gap_days and (max_span_days is None or span <= max_span_days):
                cur.append(im)
                continue
        groups.append([im])
    return [Group(index=k, images=g) for k, g in enumerate(groups)]


def tries_joint(groups: list[Group], cfg) -> bool:
    """Will the run reconstruct its date groups jointly (sfm.joint_groups: two or more groups of
    two or more images each, matched across dates into one frame and one upgrade)? The sparse
    stage does so, and the pre-flight counts the GCPs over all the groups' images then."""
    return bool(cfg.sfm.joint_groups) and len(groups) > 1 and all(len(g.images) >= 2 for g in groups)
