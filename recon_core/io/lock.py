"""One job per output folder: an advisory lock held for the whole of a run.

Two jobs writing into one OUT destroy each other (the second one's start-up removes the first
one's live scratch; both write the same products). Every job that writes into OUT (`aerec run`,
the viewer's worker, the pipeline called from Python) holds an exclusive `flock` on the folder
OUT itself, which the kernel releases when the holder ends, however it ends (kill -9 included):
a lock left by a dead job never blocks, and no file can be deleted from under it (a lock on a
file in OUT was lost when the file was deleted: a second job then came in and removed the
first one's scratch). OUT/.aerec.lock says who holds it (PID, command, since when) so a refused
job can name the holder; without it the holder is "another job". Where the filesystem cannot
lock a folder exclusively (NFS), OUT/.aerec.lockfile, which no job removes, is locked instead.

The lock is re-entrant within a process (the viewer's worker runs the pipeline, which takes it
again), and a job that holds it knows that any scratch it finds in OUT is a dead job's.
"""

from __future__ import annotations

import fcntl
import json
import os
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Iterator

from recon_core.errors import InputError

LOCK_NAME = ".aerec.lock"           # who holds the folder (PID, command, since when)
FALLBACK_NAME = ".aerec.lockfile"   # what is locked where a folder cannot be (NFS); never removed
_held: dict[str, list] = {}            # real path of OUT -> [fd, depth]
_guard = threading.Lock()


def _open_folder(out: Path) -> int:
    """A descriptor of the folder OUT, the thing locked."""
    try:
        return os.open(out, os.O_RDONLY | os.O_DIRECTORY)
    except NotADirectoryError:
        raise InputError(out, "is not a folder") from None
    except OSError as exc:
        raise InputError(out, f"cannot open this folder ({exc.strerror or exc})") from None


def _info(out: Path) -> dict:
    """What OUT/.aerec.lock says of the holder ({} when it is missing or unreadable)."""
    try:
        return json.loads((Path(out) / LOCK_NAME).read_text() or "{}")
    except (OSError, ValueError, UnicodeDecodeError):
        return {}


def holder(out: str | Path) -> dict | None:
    """Who holds OUT's lock as its information file says ({} when unknown), or None when no one
    does."""
    try:
        fd, _ = _lock_fd(Path(out))
    except InputError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _info(Path(out))
        except OSError:
            return None
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


def describe(info: dict | None) -> str:
    """'PID 1234, `aerec run site --out out`, since 10:02:03' (what is known of it)."""
    if not info:
        return "another job"
    parts = [f"PID {info['pid']}" if "pid" in info else "another job"]
    if info.get("command"):
        parts.append(f"`{info['command']}`")
    if info.get("since"):
        parts.append("since " + time.strftime("%H:%M:%S", time.localtime(info["since"])))
    return ", ".join(parts)


@contextmanager
def out_lock(out: str | Path, wait: bool = False,
             on_wait: Callable[[str], None] | None = None) -> Iterator[None]:
    """Hold OUT's lock for the block (OUT must exist). Another job holding it: InputError naming
    it, or, with `wait`, wait for it (on_wait is told whom once)."""
    out = Path(out)
    key = os.path.realpath(out)
    with _guard:
        if key in _held:
            _held[key][1] += 1
            fd = None
        else:
            fd = _acquire(out, wait, on_wait)
            _held[key] = [fd, 1]
    try:
        yield
    finally:
        with _guard:
            entry = _held[key]
            entry[1] -= 1
            if entry[1] == 0:
                del _held[key]
                try:
                    (out / LOCK_NAME).unlink(missing_ok=True)
                except OSError:
                    pass
                os.close(entry[0])                # releases the flock


def _lock_fd(out: Path) -> tuple[int, bool]:
    """A descriptor to lock: the folder itself, or, where the filesystem cannot lock a folder
    exclusively (NFS emulates flock with fcntl locks, which need a descriptor open for writing),
    OUT/.aerec.lockfile, a file no job ever removes. (descriptor, whether it is the folder)"""
    fd = _open_folder(out)
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)      # can this filesystem lock a folder?
        fcntl.flock(fd, fcntl.LOCK_UN)
        return fd, True
    except BlockingIOError:
        return fd, True                                      # it can: someone holds it
    except OSError:
        os.close(fd)
    try:
        return os.open(out / FALLBACK_NAME, os.O_RDWR | os.O_CREAT, 0o644), False
    except OSError as exc:
        raise InputError(out / FALLBACK_NAME, f"cannot lock this folder ({exc.strerror or exc})") from None


def _acquire(out: Path, wait: bool, on_wait) -> int:
    path = out / LOCK_NAME
    if path.is_dir() or (path.exists() and not path.is_file()):
        raise InputError(path, "is not a file: it is where a job says it holds this folder; remove it")
    fd, _ = _lock_fd(out)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        who = describe(holder(out))
        if not wait:
            os.close(fd)
            raise InputError(out, f"in use by {who}; one job per output folder: wait for it to end "
                                  "(or pass --wait), or choose another --out") from None
        if on_wait is not None:
            on_wait(f"{out}: in use by {who}; waiting for it to end")
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError as exc:
        os.close(fd)
        raise InputError(out, f"cannot lock this folder ({exc.strerror or exc})") from None
    info = {"pid": os.getpid(), "command": " ".join(_command()), "since": time.time()}
    try:
        tmp = out / f".aerec.lock.{os.getpid()}.tmp"
        tmp.write_text(json.dumps(info))
        tmp.replace(path)
    except OSError as exc:
        os.close(fd)
        raise InputError(path, f"cannot write it ({exc.strerror or exc}): the folder must be writable") from None
    return fd


def _command() -> list[str]:
    argv = list(sys.argv)
    if argv and argv[0].endswith(("/aerec", "aerec")):
        argv[0] = "aerec"
    return argv[:8] + (["..."] if len(argv) > 8 else [])


def is_locked_by_me(out: str | Path) -> bool:
    return os.path.realpath(out) in _held
