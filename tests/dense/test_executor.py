"""Tile-pair work through the executor: process pool and a Dask LocalCluster give the same points."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.cli import probe_scheduler
from recon_core.config import preset
from recon_core.dense.executor import LocalExecutor, SerialExecutor
from recon_core.dense.reconstruct import reconstruct_dense_group
from recon_core.errors import InputError


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


def test_scheduler_that_is_not_dask_is_refused_in_time(tmp_path, capsys):
    """--scheduler pointing at a TCP server that is not a Dask scheduler used to hang forever;
    unreachable used to end in a traceback: now one line, exit 2, before any compute."""
    import socket
    import time

    pytest.importorskip("distributed")
    from recon_core.cli import main

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(1)                                   # accepts, never speaks Dask
    port = srv.getsockname()[1]
    try:
        t0 = time.time()
        with pytest.raises(InputError, match="no Dask scheduler answered"):
            probe_scheduler(f"tcp://127.0.0.1:{port}", timeout_s=6.0)
        assert time.time() - t0 < 15
    finally:
        srv.close()
    with pytest.raises(InputError, match="not an address"):
        probe_scheduler("http://a b")
    assert main(["run", str(tmp_path), "--out", str(tmp_path / "o"), "--quiet",
                 "--scheduler", "tcp://127.0.0.1:1"]) == 2
    err = capsys.readouterr().err
    assert "--scheduler tcp://127.0.0.1:1: cannot reach a Dask scheduler" in err and "Traceback" not in err


def test_dask_local_cluster_matches_local(tiny_run):
    distributed = pytest.importorskip("distributed")
    from recon_core.dense.executor import DaskExecutor

    state, _ = tiny_run
    a, _ = _cloud(state, SerialExecutor())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        b, summary = _cloud(state, DaskExecutor(client))
        assert probe_scheduler(cluster.scheduler_address) == 2      # what `--scheduler` checks first
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert summary["points"] == len(a)
