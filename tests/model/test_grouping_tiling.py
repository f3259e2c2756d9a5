"""Date grouping and the tile grid."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from recon_core.io.site import ImageInfo
from recon_core.model.grouping import group_by_date
from recon_core.model.tiling import tile_image, tile_layout


def _im(name: str, day: float) -> ImageInfo:
    t = datetime(2020, 1, 1, tzinfo=timezone.utc) + timedelta(days=day)
    return ImageInfo(name, Path(name), 10, 10, 1, "uint16", None, t, "test", False)


def test_groups_split_at_gap():
    ims = [_im("c", 30.0), _im("a", 0.0), _im("b", 14.9), _im("d", 100.0)]
    groups = group_by_date(ims, 15.0, None)
    assert [[im.name for im in g.images] for g in groups] == [["a", "b"], ["c"], ["d"]]


def test_gap_of_exactly_threshold_splits():
    groups = group_by_date([_im("a", 0.0), _im("b", 15.0)], 15.0, None)
    assert len(groups) == 2


def test_span_cap_breaks_long_chains():
    ims = [_im(f"i{k}", 10.0 * k) for k in range(10)]  # regular acquisitions, 10 days apart
    assert len(group_by_date(ims, 15.0, None)) == 1
    capped = group_by_date(ims, 15.0, 30.0)
    assert len(capped) > 1 and all(g.span_days <= 30.0 for g in capped)


@pytest.mark.parametrize("length,d", [(2000, 1000), (2500, 1000), (999, 1000), (5000, 1000),
                                      (437, 300), (1024, 1000), (1700, 1000), (8192, 1000)])
def test_tile_layout_covers_with_overlap(length, d):
    overlap = d // 3
    starts, size = tile_layout(length, d, overlap)
    assert size <= 1.1 * d + 1 and (size >= d or size == length)
    ends = [s + size for s in starts]
    assert starts[0] == 0 and ends[-1] == length      # the last tile ends at the border
    for e0, s1 in zip(ends, starts[1:]):
        assert e0 - s1 >= overlap                     # neighbours overlap by at least d/3
    if len(starts) > 1:                               # no near-duplicate tiles
        assert min(b - a for a, b in zip(starts, starts[1:])) >= (d - overlap) / 2


def test_slightly_larger_image_is_one_tile():
    assert tile_layout(1024, 1000, 333) == ([0], 1024)


def test_tiles_clip_and_keep_offsets():
    tiles = tile_image("x.tif", 2500, 1200, d=1000)
    assert all(1000 <= t.width <= 1100 and t.height == 1000 for t in tiles)
    assert max(t.col0 + t.width for t in tiles) == 2500
    t = tiles[-1]
    assert t.contains(np.array([[t.col0 + 10, t.row0 + 10]]))[0]
    small = tile_image("s.tif", 400, 300, d=1000)
    assert len(small) == 1 and (small[0].width, small[0].height) == (400, 300)
