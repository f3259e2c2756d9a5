"""The dense stage: every group's dense affine cloud, streamed to affine/group_<k>/dense.ply."""

from __future__ import annotations

from typing import TYPE_CHECKING

from recon_core.dense.matchers import make_matcher
from recon_core.dense.reconstruct import reconstruct_dense_group
from recon_core.events import EventBus

if TYPE_CHECKING:
    from recon_core.context import RunState


def run(state: RunState, bus: EventBus) -> dict:
    out = {"groups": {}}
    images = {im.name: im for im in state.site.images}
    matcher = make_matcher(state.cfg)
    for g, model in sorted(state.models.items()):
        path = state.layout.dense_ply(g)
        _, summary = reconstruct_dense_group(model, images, state.cfg.dense, bus, path=path,
                                             matcher=matcher)
        state.dense[g] = path
        out["groups"][str(g)] = summary
    return out


def load(state) -> None:
    for g in state.models:
        if state.layout.dense_ply(g).exists():
            state.dense[g] = state.layout.dense_ply(g)
