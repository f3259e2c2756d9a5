"""Feature tracks: connected components of verified matches across the images of a group."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from recon_core.sparse.matching import PairMatches


@dataclass
class Tracks:
    """Track membership of features: node k is feature `feat[k]` of image `img[k]`."""

    img: np.ndarray        # (k,) image index of each node
    feat: np.ndarray       # (k,) feature index within its image
    track: np.ndarray      # (k,) track id, 0..n_tracks-1
    n_tracks: int

    def lengths(self) -> np.ndarray:
        return np.bincount(self.track, minlength=self.n_tracks)


def build_tracks(n_features: list[int], pairs: list[tuple[int, int, PairMatches]]) -> Tracks:
    """Union of all pairwise matches (image indices a, b); tracks seeing one image twice are dropped."""
    offsets = np.concatenate([[0], np.cumsum(n_features)])
    a_nodes, b_nodes = [], []
    for a, b, pm in pairs:
        a_nodes.append(offsets[a] + pm.idx_i)
        b_nodes.append(offsets[b] + pm.idx_j)
    if not a_nodes:
        z = np.zeros(0, np.int64)
        return Tracks(z, z, z, 0)
    u, v = np.concatenate(a_nodes), np.concatenate(b_nodes)
    nodes = np.unique(np.concatenate([u, v]))
    ui, vi = np.searchsorted(nodes, u), np.searchsorted(nodes, v)
    g = coo_matrix((np.ones(len(ui)), (ui, vi)), shape=(len(nodes), len(nodes)))
    _, label = connected_components(g, directed=False)
    img = np.searchsorted(offsets, nodes, side="right") - 1
    feat = nodes - offsets[img]
    # A track with two features in one image is inconsistent: drop it whole.
    key = label * (len(n_features) + 1) + img
    _, counts = np.unique(key, return_counts=True)
    bad_key = np.unique(key)[counts > 1]
    bad_track = np.unique(bad_key // (len(n_features) + 1))
    keep = ~np.isin(label, bad_track)
    img, feat, label = img[keep], feat[keep], label[keep]
    uniq, track = np.unique(label, return_inverse=True)
    return Tracks(img.astype(np.int64), feat.astype(np.int64), track.astype(np.int64), len(uniq))
