"""Tile-pair work through the executor: process pool and a Dask LocalCluster give the same points."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.config import preset
from recon_core.dense.executor import LocalExecutor, SerialExecutor
from recon_core.dense.reconstruct import reconstruct_dense_group


def _cloud(state, executor):
    images = {im.name: im for im in state.site.images}
    cfg = preset("tiny").dense
    cloud, summary = reconstruct_dense_group(state.models[0], images, cfg, executor=executor)
    return cloud, summary


def test_process_pool_matches_serial(tiny_run):
    state, _ = tiny_run
    a, _ = _cloud(state, SerialExecutor())
    with LocalExecutor(2) as ex:
        b, _ = _cloud(state, ex)
    assert len(a) > 1000
    np.testing.assert_array_equal(a.xyz, b.xyz)


def test_dask_local_cluster_matches_local(tiny_run):
    distributed = pytest.importorskip("distributed")
    from recon_core.dense.executor import DaskExecutor

    state, _ = tiny_run
    a, _ = _cloud(state, SerialExecutor())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        b, summary = _cloud(state, DaskExecutor(client))
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert summary["points"] == len(a)
