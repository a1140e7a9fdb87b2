"""Torch files on disk: tensor-only reading with one-line errors, and atomic saving.

Every checkpoint reader of the project (DynPT, CoTracker3, DUSt3R family, RAFT, the pointmap
trainer) goes through `require_file` and `load_failure`, so a folder, a missing file, random
bytes, a file cut short or one holding Python objects is named the same way everywhere; files are
saved through `save_atomic` (a temporary sibling renamed into place).
"""

from __future__ import annotations

import errno
import os
import pickle
import re
import warnings
from pathlib import Path

import torch

from c4d_core.errors import UserError
from c4d_core.files import atomic_path, check_regular_file, disk_error
from c4d_core.sniff import TORCH, ZIP, file_format


def require_file(path: Path, what: str, missing_hint: str) -> None:
    """`UserError` unless `path` is a regular file: a folder is named as one (with the checkpoint
    files in it or one level down), a named pipe or a device (/dev/zero) as what it is, a missing
    path says so and adds `missing_hint`."""
    if path.is_dir():
        inside = [str(p.relative_to(path)) for pattern in ("*.pt", "*.pth", "*/*.pt", "*/*.pth")
                  for p in sorted(path.glob(pattern))]
        held = f" (it holds {', '.join(inside[:3])})" if inside else ""
        raise UserError(f"{what} {str(path)!r} is a folder, not a file{held}; pass the checkpoint "
                        "file inside it")
    check_regular_file(path, what, "pass a checkpoint file")
    if not path.is_file():
        raise UserError(f"{what} {str(path)!r} does not exist; {missing_hint}")


def holds_objects(exc: Exception) -> bool:
    """Whether a tensor-only `torch.load` failed on a Python object it may not build (a pickled
    class), rather than on bytes that are no pickle at all."""
    return isinstance(exc, pickle.UnpicklingError) and bool(
        re.search(r"Unsupported global|GLOBAL |allowlisted via", str(exc)))


def other_format(path: Path) -> str | None:
    """What `path` is where it is plainly no PyTorch file (a plain pickle, an image, JSON, ...:
    `c4d_core.sniff`); None for PyTorch's layouts (a zip archive, its legacy pickle), whole or cut
    short, and for bytes of no known format."""
    kind = file_format(path)
    return None if kind in (None, ZIP, TORCH) else kind


def load_failure(exc: Exception, path: Path) -> str:
    """Why `torch.load(path, weights_only=True)` failed, in a few words. PyTorch's own text is never
    passed on: it advises loading with weights_only=False (unsafe for a file of unknown origin),
    carries terminal colour codes, and says "weights_only" even for random bytes."""
    if holds_objects(exc):
        found = (re.search(r"GLOBAL ([\w.]+)", str(exc))
                 or re.search(r"allowlisted via `?\w+`?, but got <class '([\w.]+)'>", str(exc)))
        return ("it holds Python objects other than tensors and plain values"
                + (f" ({found[1]})" if found else ""))
    if isinstance(exc, OSError) and exc.errno not in (None, errno.EINVAL) and exc.strerror:
        return exc.strerror  # the file itself cannot be read (permissions, I/O error)
    other = other_format(path)
    if other:
        return f"it is {other}, not a PyTorch file"
    try:
        size = f"{path.stat().st_size} bytes"
    except OSError:
        size = "size unknown"
    # zip or pickle errors, EOF, EINVAL (a zip cut inside a record), miniz's "failed finding
    # central directory", an unknown pickle opcode: all a file cut short or of another kind
    return f"not a PyTorch file, or truncated ({size})"


def save_atomic(path: str | os.PathLike, payload) -> Path:
    """`torch.save(payload)` to `path` atomically; a failed write (disk full) is a `UserError`."""
    path = Path(path)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:  # a handle: no temporary name inside
        try:
            torch.save(payload, fh)
        except RuntimeError as exc:  # PyTorch's writer turns the OSError of a full disk into this
            cause = exc.__cause__ or exc.__context__
            if isinstance(cause, OSError) and cause.errno is not None:
                raise disk_error(path, cause) from exc
            if "write" not in str(exc).lower():
                raise
            raise disk_error(path, OSError(errno.ENOSPC, "the file could not be written")) from exc
    return path


def read_tensor_file(path: Path, kind: str, missing_hint: str, damaged_hint: str,
                     foreign_hint: str | None = None):
    """`torch.load(path, weights_only=True)` on the CPU; a missing or unreadable file is a one-line
    `UserError` ("<kind> checkpoint ... does not exist; <missing_hint>" / "...; <damaged_hint>");
    a folder is named as one. An intact file of another kind (Python objects beyond tensors, an
    image, JSON, ...) gets `foreign_hint` instead of `damaged_hint` where given."""
    require_file(path, f"{kind} checkpoint", missing_hint)
    try:
        with warnings.catch_warnings():  # torch's note on a plain pickle's protocol: noise here
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a damaged file can fail anywhere inside the unpickler
        intact = holds_objects(exc) or other_format(path) is not None
        hint = foreign_hint if intact and foreign_hint else damaged_hint
        raise UserError(f"cannot read {str(path)!r} as a {kind} checkpoint "
                        f"({load_failure(exc, path)}); {hint}") from exc
