"""Writing files so that nothing already written is lost: a temporary sibling, then a rename.

Every package writes its outputs (shard index records, checkpoints, track files, reports,
pictures, reconstructions) through `atomic_path`: the data goes to a hidden temporary file next to
the target, which is renamed over it only once complete. A crash or a full disk leaves the old
file (or none), never a half-written one, so re-running a command resumes from what exists.
An output that is a folder of many files read as one (a reconstruction) is written whole into
`staged_folder`'s sibling and put in place when complete.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from c4d_core.errors import UserError


# errno values of a failed write that the user fixes by choosing another place (or freeing space)
DISK_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES,
                         errno.EPERM, errno.ENOTDIR, errno.EISDIR, errno.EEXIST})


def _lstat_or_none(path: Path) -> os.stat_result | None:
    """`os.lstat(path)`, or None when it cannot be read (missing, name too long, no access)."""
    try:
        return os.lstat(path)
    except OSError:
        return None


def disk_error(path: str | os.PathLike, exc: OSError, verb: str = "write") -> UserError:
    """The `UserError` for a failed `verb` ("write", or "use" when unknown) of `path`, with the
    advice that fits `exc.errno` (disk full, permissions, read-only disk, a file or a dangling
    symbolic link where a folder should be, a missing folder, a name too long)."""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        why = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
               errno.EFBIG: "file size limit exceeded"}[exc.errno]
        return UserError(
            f"{why} while writing {path}; free some space or choose another "
            "output folder, then run the same command again: finished files are kept"
        )
    if exc.errno == errno.ENAMETOOLONG:
        return UserError(f"cannot {verb} {path}: the name is too long for the file system (at most "
                         "255 bytes per name); choose a shorter path")
    target = Path(exc.filename if isinstance(exc.filename, (str, os.PathLike)) else path)
    nearest, missing = target, None  # the nearest existing entry, the missing folder below it
    for entry in (target, *target.parents):
        if _lstat_or_none(entry) is not None:
            nearest = entry
            break
        missing = entry
    if os.path.islink(nearest) and not os.path.exists(nearest):
        return UserError(f"cannot {verb} {path}: {nearest} is a dangling symbolic link (to "
                         f"{os.readlink(nearest)}, which does not exist); remove it or choose "
                         "another output folder")
    if exc.errno in (errno.ENOTDIR, errno.EEXIST) and not os.path.isdir(nearest):
        return UserError(f"cannot {verb} {path}: {nearest} is a file, not a folder; choose "
                         "another output folder")
    if exc.errno == errno.ENOENT and nearest != target:
        if nearest != target.parent:
            return UserError(f"cannot {verb} {path}: the folder {missing} does not exist; "
                             "create it or choose another output folder")
        return UserError(f"cannot {verb} {path}: {target} does not exist and cannot be created "
                         f"in {nearest} (a system folder?); check the path or choose another "
                         "output folder")
    return UserError(f"cannot {verb} {path}: {exc.strerror or exc}; choose a writable output folder")


def remove_quietly(path: Path) -> None:
    """Delete `path` if it exists; a failure (read-only disk, a file as folder) is not reported,
    so that it never hides the error that made the cleanup necessary."""
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


def remove_empty_folders(path: Path) -> None:
    """Delete `path` and the folders below it if none holds a file (what a failed command created
    before it wrote anything); anything else is left, and a failure is not reported."""
    try:
        for folder in sorted((p for p in path.rglob("*") if p.is_dir()), reverse=True):
            folder.rmdir()
        path.rmdir()
    except OSError:
        pass


def make_folder(path: str | os.PathLike) -> Path:
    """Create the folder `path` and its parents (an existing one is fine); returns `path`. A
    failure (a file or a dangling link in the way, a read-only disk) becomes a `UserError`."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise disk_error(path, exc) from exc
    return path


@contextlib.contextmanager
def staged_folder(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a sibling folder `PATH.partial` to write a whole output folder into; when the block
    succeeds it becomes `path`, at once.

    A folder already at `path` (a finished output the caller decided to replace, or an empty
    folder) is kept untouched until then: the old folder is renamed aside and removed after the
    new one is in place, an empty one receives the entries. On any exception the partial folder
    is removed and `path` is as it was, so readers never see half an output or two outputs mixed.
    """
    path = Path(path)
    stage = path.with_name(path.name + ".partial")
    shutil.rmtree(stage, ignore_errors=True)  # a leftover of a killed run
    try:
        stage.mkdir(parents=True)
        yield stage
        if not path.exists():
            os.replace(stage, path)
        elif not any(path.iterdir()):  # an empty folder the user made (maybe a mount point)
            for entry in stage.iterdir():
                os.replace(entry, path / entry.name)
            stage.rmdir()
        else:
            old = path.with_name(f".{path.name}.old{os.getpid()}")
            os.replace(path, old)
            os.replace(stage, path)
            shutil.rmtree(old, ignore_errors=True)
    except OSError as exc:
        if exc.errno is None:
            raise
        raise disk_error(exc.filename or path, exc) from exc
    finally:
        shutil.rmtree(stage, ignore_errors=True)


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
        remove_quietly(tmp)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically; returns `path`."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically; returns `path`."""
    return write_bytes(path, text.encode("utf-8"))


def append_line(path: str | os.PathLike, line: str) -> None:
    """Append `line` and a newline to the text file `path` (created if missing) in one write.

    If the write fails part-way (disk full), the file is cut back to its old length, so it never
    ends in a half line; the error becomes a `UserError` naming the file.
    """
    data = (line + "\n").encode("utf-8")
    try:
        fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    except OSError as exc:
        raise disk_error(path, exc) from exc
    try:
        size = os.fstat(fd).st_size
        try:
            written = os.write(fd, data)
            if written != len(data):
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        except OSError as exc:
            try:
                os.ftruncate(fd, size)
            except OSError:
                pass  # the append was not made at all
            raise disk_error(path, exc) from exc
    finally:
        os.close(fd)


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


# What an existing path that is no regular file is, by pathlib's tests (each follows symbolic links).
_NOT_REGULAR = ((Path.is_dir, "a folder"), (Path.is_fifo, "a named pipe"), (Path.is_socket, "a socket"),
                (Path.is_char_device, "a character device"), (Path.is_block_device, "a block device"))


def special_file_kind(path: str | os.PathLike) -> str | None:
    """What `path` is where it exists but is no regular file ("a folder", "a named pipe", "a socket",
    "a character device", "a block device"); None for a regular file (or a symbolic link to one)
    and for a path that does not exist or cannot be examined."""
    path = Path(path)
    return next((kind for test, kind in _NOT_REGULAR if test(path)), None)


def check_regular_file(path: str | os.PathLike, what: str, hint: str) -> Path:
    """`path` as a Path, or a `UserError` ("<what> PATH is a named pipe, not a regular file; <hint>")
    where it exists but is no regular file: opened, a named pipe waits for a writer forever and a
    character device such as /dev/zero never ends. Every reader of a user's input file calls this
    before opening it. A missing path passes: the reader's own open names it as missing."""
    kind = special_file_kind(path)
    if kind is not None:
        raise UserError(f"{what} {os.fspath(path)} is {kind}, not a regular file; {hint}")
    return Path(path)
