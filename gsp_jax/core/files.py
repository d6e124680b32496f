"""Files that survive crashes and concurrent runs: atomic writes, checked reads, and a lock per output folder.

* `write_text`, `write_json`, `write_bytes`, `savez` write to a unique temporary name in the target's folder, flush it
  to disk, then rename it over the target (atomic on POSIX): a reader sees the old file or the new one, never half of
  one, and two writers never share a temporary file.
* `read_json(path)` raises `UnreadableFile` naming the path when a file is missing, truncated or not JSON; callers that
  can recompute (`reuse_json`) warn with the path and recompute instead.
* `folder_lock(folder)` holds ``<folder>/.gsp_jax.lock`` (the owner's process id and command line) for the life of a
  run; a second run on the same folder is refused with a message naming the folder and the owner, and a lock whose
  process is gone (a crash) is taken over with a warning.
"""
from __future__ import annotations

import atexit
import contextlib
import io
import json
import os
import pathlib
import sys
import tempfile
import warnings

import numpy as np

LOCK_NAME = ".gsp_jax.lock"


class UnreadableFile(ValueError):
    """A saved file is missing, truncated or not in its format; the message names the path."""


class FolderInUse(RuntimeError):
    """Another live process holds the folder's lock; the message names the folder and the process."""


def write_bytes(path, data: bytes) -> pathlib.Path:
    """Write `data` to `path` atomically (a unique temporary file in the same folder, then a rename)."""
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise
    return path


def write_text(path, text: str) -> pathlib.Path:
    return write_bytes(path, text.encode())


def write_json(path, obj, indent: int | None = 1, **kwargs) -> pathlib.Path:
    """`json.dumps(obj)` written atomically (a trailing newline)."""
    return write_text(path, json.dumps(obj, indent=indent, **kwargs) + "\n")


def savez(path, compressed: bool = False, **arrays) -> pathlib.Path:
    """`numpy.savez` (or `savez_compressed`) written atomically."""
    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return write_bytes(path, buf.getvalue())


def read_json(path):
    """The JSON at `path`; `UnreadableFile` naming the path if it is missing, truncated or not JSON."""
    path = pathlib.Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UnreadableFile(f"{path}: no such file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise UnreadableFile(f"{path}: not readable JSON ({e}); truncated by a crash?") from None


def reuse_json(path, valid=lambda obj: True):
    """A saved result to reuse, or None (recompute) when there is none; one that is unreadable or fails `valid` is
    reported with a warning naming the file, and None is returned so that the caller recomputes and rewrites it."""
    path = pathlib.Path(path)
    if not path.exists():
        return None
    try:
        obj = read_json(path)
    except UnreadableFile as e:
        warnings.warn(f"{e}: recomputing it", stacklevel=2)
        return None
    if not valid(obj):
        warnings.warn(f"{path}: not a result of this command (unexpected contents): recomputing it", stacklevel=2)
        return None
    return obj


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


@contextlib.contextmanager
def folder_lock(folder):
    """Hold `folder`'s lock for the block: `FolderInUse` naming the folder and the owner if another live process
    holds it; a stale lock (its process is gone) is taken over with a warning. Re-entrant within a process."""
    folder = pathlib.Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lock = folder / LOCK_NAME
    me = {"pid": os.getpid(), "command": " ".join(sys.argv)}
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                owner = json.loads(lock.read_text())
                pid = int(owner["pid"])
            except (OSError, ValueError, KeyError, TypeError):
                owner, pid = {"pid": "?", "command": "?"}, -1
            if pid == os.getpid():  # this process already holds it
                yield lock
                return
            if pid > 0 and _alive(pid):
                raise FolderInUse(f"{folder}: in use by process {pid} ({owner.get('command', '?')}); wait for it or "
                                  f"use another folder (remove {lock} if that process is not a gsp_jax run)") from None
            warnings.warn(f"{lock}: stale lock of process {owner.get('pid')} (no longer running): taking it over",
                          stacklevel=3)
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()
            continue
        with os.fdopen(fd, "w") as f:
            f.write(json.dumps(me))
        try:
            yield lock
        finally:
            with contextlib.suppress(FileNotFoundError):
                lock.unlink()
        return
    raise FolderInUse(f"{folder}: could not take its lock {lock}")


_HELD = contextlib.ExitStack()  # the folders this process holds until it exits (`hold`)
atexit.register(_HELD.close)


def hold(folder) -> pathlib.Path:
    """Take `folder`'s lock (`folder_lock`) for the rest of this process (released at exit; a crash leaves a stale
    lock that the next run takes over): `FolderInUse` if another live process holds it. Returns the folder. Holding
    a folder this process already holds changes nothing (`folder_lock` is re-entrant)."""
    _HELD.enter_context(folder_lock(folder))
    return pathlib.Path(folder)

