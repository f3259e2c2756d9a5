"""Tile-pair work through the executor: process pool and a Dask LocalCluster give the same points."""

from __future__ import annotations

import numpy as np
import pytest

from recon_core.cli import main, probe_scheduler
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


def test_a_scheduler_from_the_configuration_file_is_named_so(tiny_site, tmp_path, capsys):
    pytest.importorskip("distributed")
    cfg = tmp_path / "my.toml"
    cfg.write_text('[dense]\nscheduler = "tcp://127.0.0.1:1"\n')
    assert main(["run", str(tiny_site), "--out", str(tmp_path / "o"), "--quiet", "--config", str(cfg)]) == 2
    err = capsys.readouterr().err
    assert f"dense.scheduler (in {cfg}) tcp://127.0.0.1:1: cannot reach" in err and "--scheduler" not in err


def test_dask_local_cluster_matches_local(tiny_run, tmp_path):
    distributed = pytest.importorskip("distributed")
    from recon_core.dense.executor import DaskExecutor

    state, _ = tiny_run
    a, _ = _cloud(state, SerialExecutor())
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None, local_directory=str(tmp_path)) as cluster, \
            distributed.Client(cluster) as client:
        b, summary = _cloud(state, DaskExecutor(client))
        assert probe_scheduler(cluster.scheduler_address) == 2      # what `--scheduler` checks first
    np.testing.assert_array_equal(a.xyz, b.xyz)
    assert summary["points"] == len(a)


def _slow(x):
    import time

    time.sleep(0.5)
    return x


def test_a_distributed_run_whose_workers_are_gone_says_so_and_ends(tmp_path):
    """The only worker gone mid-run: after a bounded wait the executor says so, and if none comes
    back it ends with a clear error instead of waiting for ever."""
    distributed = pytest.importorskip("distributed")
    from recon_core.dense.executor import DaskExecutor
    from recon_core.errors import ReconstructionError

    told = []
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None, local_directory=str(tmp_path)) as cluster, \
            distributed.Client(cluster) as client:
        ex = DaskExecutor(client, on_wait=told.append, warn_s=1.0, give_up_s=4.0, poll_s=0.5)
        got = []
        with pytest.raises(ReconstructionError, match="no worker for .* none came back"):
            for k, r in enumerate(ex.map_unordered(_slow, range(40))):
                got.append(r)
                if k == 1:
                    cluster.scale(0)
        assert 2 <= len(got) < 40
        assert told and "no worker" in told[0] and "waiting for one to come back" in told[0]
