"""Writing files so that nothing already written is lost: a temporary sibling, then a rename.

Every package writes its outputs (shard index records, checkpoints, track files, reports,
pictures, reconstructions) through `atomic_path`: the data goes to a hidden temporary file next to
the target, which is renamed over it only once complete. A crash or a full disk leaves the old
file (or none), never a half-written one, so re-running a command resumes from what exists.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from c4d_core.errors import UserError


def disk_error(path: str | os.PathLike, exc: OSError) -> UserError:
    """The `UserError` for a failed write of `path` (disk full, permissions, read-only disk)."""
    if exc.errno == errno.ENOSPC:
        return UserError(
            f"no space left on the device while writing {path}; free some space or choose another "
            "output folder, then run the same command again: finished files are kept"
        )
    return UserError(f"cannot write {path}: {exc.strerror or exc}; choose a writable output folder")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of `path` to write; rename it onto `path` when the block succeeds.

    The temporary name keeps the suffix (`.x.tmp<pid>.png` for `x.png`), so writers that choose
    the format by extension work unchanged. The parent folder is created. On any exception the
    temporary file is removed and `path` is untouched; an error of the operating system (disk
    full, permissions) becomes a `UserError` naming the file.
    """
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        yield tmp
        with open(tmp, "rb") as fh:  # on disk before the rename makes it visible
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if exc.errno is None:  # a writer's own OSError (e.g. an unsupported codec): keep it
            raise
        raise disk_error(path, exc) from exc
    finally:
        tmp.unlink(missing_ok=True)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically; returns `path`."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically; returns `path`."""
    return write_bytes(path, text.encode("utf-8"))


def json_default(value: Any) -> Any:
    """`json.dumps(default=...)` for numpy scalars and arrays (numbers, lists) and paths (strings)."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_json(path: str | os.PathLike, value: Any, indent: int = 2) -> Path:
    """Write `value` as indented JSON (numpy values allowed) to `path` atomically."""
    return write_text(path, json.dumps(value, indent=indent, default=json_default) + "\n")
