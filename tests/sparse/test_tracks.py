"""Tracks from pairwise matches: union of matches, inconsistent components dropped."""

from __future__ import annotations

import numpy as np

from recon_core.sparse.matching import PairMatches
from recon_core.sparse.tracks import build_tracks


def test_tracks_drop_inconsistent_components():
    # image 0 feature 0 matches image 1 features 0 and 1 -> one track sees image 1 twice: dropped
    pm01 = PairMatches("a", "b", np.array([0, 0, 2]), np.array([0, 1, 2]))
    pm12 = PairMatches("b", "c", np.array([2]), np.array([5]))
    t = build_tracks([3, 3, 6], [(0, 1, pm01), (1, 2, pm12)])
    assert t.n_tracks == 1
    assert sorted(zip(t.img.tolist(), t.feat.tolist())) == [(0, 2), (1, 2), (2, 5)]


def test_chains_through_three_images_become_one_track_each():
    pm01 = PairMatches("a", "b", np.array([0, 1, 4]), np.array([3, 2, 0]))
    pm12 = PairMatches("b", "c", np.array([3, 2]), np.array([7, 8]))
    pm02 = PairMatches("a", "c", np.array([0]), np.array([7]))            # closes the first loop
    t = build_tracks([5, 4, 9], [(0, 1, pm01), (1, 2, pm12), (0, 2, pm02)])
    got = sorted(sorted(zip(t.img[t.track == k].tolist(), t.feat[t.track == k].tolist()))
                 for k in range(t.n_tracks))
    assert got == [[(0, 0), (1, 3), (2, 7)], [(0, 1), (1, 2), (2, 8)], [(0, 4), (1, 0)]]

