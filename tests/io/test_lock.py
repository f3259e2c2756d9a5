"""One job per output folder (recon_core.io.lock), and outputs never inside the site."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from recon_core.cli import main
from recon_core.io.lock import holder, out_lock

HOLD = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from recon_core.io.lock import out_lock
    out = Path(sys.argv[1])
    with out_lock(out):
        # a live job's scratch, as the dense stage leaves it while it runs
        (out / ".dense_parts_live1234").mkdir(exist_ok=True)
        print("held", flush=True)
        time.sleep(float(sys.argv[2]))
""")


def _holder(out, seconds: float) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", HOLD, str(out), str(seconds)], stdout=subprocess.PIPE,
                         text=True, cwd=os.getcwd())
    assert p.stdout.readline().strip() == "held"
    return p


def test_a_second_job_is_refused_and_the_first_keeps_its_scratch(tiny_site, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    p = _holder(out, 30)
    try:
        info = holder(out)
        assert info["pid"] == p.pid
        code = main(["run", str(tiny_site), "--out", str(out), "--stage", "sparse", "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert f"PID {p.pid}" in err[0] and "--wait" in err[0]
        assert (out / ".dense_parts_live1234").is_dir()       # the live job's scratch is untouched
        assert not (out / "stages").exists()                    # nothing computed
    finally:
        p.kill()
        p.wait()


def test_a_dead_holder_never_blocks_and_wait_waits(tiny_site, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    p = _holder(out, 60)
    os.kill(p.pid, signal.SIGKILL)                               # the kernel drops its flock
    p.wait()
    assert holder(out) is None
    p = _holder(out, 3)
    t0 = time.time()
    code = main(["run", str(tiny_site), "--out", str(out), "--stage", "sparse", "--quiet", "--wait"])
    p.wait()
    assert code == 0 and time.time() - t0 >= 1.5
    assert "waiting for it to end" in capsys.readouterr().err
    assert not (out / ".dense_parts_live1234").exists()          # a dead job's scratch is swept
    assert holder(out) is None                                   # released at the end


def test_deleting_the_lock_file_does_not_let_a_second_job_in(tiny_site, tmp_path, capsys):
    """The lock is on the folder: its information file deleted mid-run, a second job is still
    refused (it names "another job") and the first one's scratch is untouched."""
    out = tmp_path / "out"
    out.mkdir()
    p = _holder(out, 30)
    try:
        (out / ".aerec.lock").unlink()
        assert holder(out) == {}
        code = main(["run", str(tiny_site), "--out", str(out), "--stage", "sparse", "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and "in use by another job" in err[0], err
        assert (out / ".dense_parts_live1234").is_dir()
    finally:
        p.kill()
        p.wait()


def test_a_lock_path_that_is_a_folder_is_named(tiny_site, tmp_path, capsys):
    out = tmp_path / "out"
    (out / ".aerec.lock").mkdir(parents=True)
    code = main(["run", str(tiny_site), "--out", str(out), "--stage", "sparse", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and ".aerec.lock" in err[0] and "not a file" in err[0], err


def test_the_lock_is_reentrant_in_one_process(tmp_path):
    with out_lock(tmp_path):
        with out_lock(tmp_path):
            assert holder(tmp_path)["pid"] == os.getpid()
        assert holder(tmp_path)["pid"] == os.getpid()
    assert holder(tmp_path) is None


@pytest.mark.parametrize("where", ["images", ".", "sub/deeper"])
def test_an_output_folder_inside_the_site_is_refused_before_any_write(tiny_site, tmp_path, capsys, where):
    import shutil

    site = tmp_path / "site"
    shutil.copytree(tiny_site, site)
    before = sorted(str(p) for p in site.rglob("*"))
    code = main(["run", str(site), "--out", str(site / where), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "inside the site" in err[0], err
    assert sorted(str(p) for p in site.rglob("*")) == before


def test_a_site_inside_the_output_folder_is_refused(tiny_site, tmp_path, capsys):
    import shutil

    site = tmp_path / "runs" / "site"
    shutil.copytree(tiny_site, site)
    code = main(["run", str(site), "--out", str(tmp_path / "runs"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "holds the site" in err[0], err


def test_the_first_job_finishes_as_if_alone(tiny_site, tiny_run, tmp_path, capsys):
    """A real `aerec run` holds OUT; a second one started during it is refused naming it; the
    first ends with the DSM of a run alone (bit for bit)."""
    import rasterio

    state, _ = tiny_run
    out = tmp_path / "out"
    first = subprocess.Popen([sys.executable, "-m", "recon_core.cli", "run", str(tiny_site), "--out", str(out),
                              "--preset", "tiny", "--quiet"], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.time()
        while holder(out) is None and first.poll() is None and time.time() - t0 < 60:
            time.sleep(0.05)
        assert holder(out) is not None, "the first job never held the folder"
        assert main(["run", str(tiny_site), "--out", str(out), "--preset", "tiny", "--quiet"]) == 2
        assert f"PID {first.pid}" in capsys.readouterr().err
        assert first.wait(300) == 0, first.stderr.read()
    finally:
        if first.poll() is None:
            first.kill()
    with rasterio.open(out / "dsm.tif") as a, rasterio.open(state.layout.dsm) as b:
        np.testing.assert_array_equal(a.read(1), b.read(1))


def test_where_a_folder_cannot_be_locked_a_file_that_stays_is(tmp_path, monkeypatch):
    """NFS emulates flock with fcntl locks, which refuse an exclusive lock on a folder (EBADF):
    the lock falls back to OUT/.aerec.lockfile, and still keeps a second job out."""
    import errno
    import fcntl as real_fcntl

    import recon_core.io.lock as lock
    from recon_core.errors import InputError

    flock = real_fcntl.flock

    def nfs_like(fd, op):
        if os.path.isdir(f"/proc/self/fd/{fd}"):
            raise OSError(errno.EBADF, "Bad file descriptor")
        return flock(fd, op)
    monkeypatch.setattr(lock.fcntl, "flock", nfs_like)
    fd = lock._acquire(tmp_path, False, None)
    try:
        assert (tmp_path / ".aerec.lockfile").is_file()
        assert lock.holder(tmp_path)["pid"] == os.getpid()
        with pytest.raises(InputError, match="in use by PID"):
            lock._acquire(tmp_path, False, None)
    finally:
        os.close(fd)
    assert lock.holder(tmp_path) is None
