"""Every command owns its outputs: a marker of the writing command's kind, and a claim before writing.

What a command writes carries the kind of command that made it:
- an output folder holds `.c4d-output.json`, `{"format": "c4d-output", "kind": KIND}`, written
  before anything else (`output_folder`);
- a single output file carries its kind inside: a top-level `"c4d_output"` key in JSON, a
  `<meta name="c4d-output">` tag in HTML, a `c4d-output` text chunk in PNG (`file_kind` reads
  them back; `mark_png` adds the chunk to a PNG another program drew).

Before writing, a command claims its output, and the claim is the same for every command:
- a folder that is new or empty is made and marked; one of the command's own kind is used as
  the command always did (resumed, or replaced where the command says so); one made by another
  kind is refused, unless the user passes `--overwrite`: then the old folder is set aside, put
  back if the command fails, and removed once the new output is complete. A folder holding
  files that c4d did not write is refused even with `--overwrite`: nothing of the user's is
  deleted.
- a file that is new is written; one of the command's own kind is replaced; any other file, or
  a new file inside a folder made by another kind (other than the companions a kind accepts,
  e.g. `eval_recon.json` in a reconstruction), is refused unless `--overwrite` (then it is
  replaced atomically: the old file stays until the new one is complete).

Folders written before markers existed are recognised by the files their kind always writes
(`LEGACY_SIGNATURES`) and are marked when their own kind claims them. Paths that a command
stores in its outputs are absolute or relative to the output folder, so a folder can be moved.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import struct
import zlib
from pathlib import Path
from typing import Callable, Iterator

from c4d_core.errors import UserError
from c4d_core.files import make_folder, remove_empty_folders, write_bytes, write_json

MARKER = ".c4d-output.json"
FORMAT = "c4d-output"
JSON_KEY = "c4d_output"  # the kind of a JSON output file, a top-level key
PNG_KEYWORD = b"c4d-output"  # the kind of a PNG output file, a tEXt chunk

# kind -> what such an output is, for messages
KINDS: dict[str, str] = {
    "datagen": "a dataset of shards made by `c4d datagen`",
    "train": "a DynPT training run made by `c4d train`",
    "pretrain-pointmaps": "a pointmap training run made by `c4d pretrain-pointmaps`",
    "eval": "tracker metrics made by `c4d eval`",
    "track": "tracks made by `c4d track`",
    "run": "a reconstruction made by `c4d run`",
    "eval-recon": "reconstruction metrics made by `c4d eval-recon`",
    "inspect": "a report made by `c4d inspect`",
    "view": "a 4D view made by `c4d view`",
    "export-kubric": "a kubric export made by `c4d export kubric`",
    "export-cotracker": "a cotracker export made by `c4d export cotracker`",
    "export-tapvid": "a tapvid export made by `c4d export tapvid`",
    "export-colmap": "a COLMAP text model made by `c4d export colmap`",
    "demo": "a demo made by `c4d demo`",
}

# (folder kind, writing kind) -> the file names that kind may add to such a folder
COMPANIONS: dict[tuple[str, str], frozenset[str]] = {
    ("run", "eval-recon"): frozenset({"eval_recon.json"}),
}


def _has(*names: str) -> Callable[[Path], bool]:
    return lambda folder: all((folder / name).exists() for name in names)


def _glob(pattern: str) -> Callable[[Path], bool]:
    return lambda folder: next(folder.glob(pattern), None) is not None


def _config_kind(folder: Path) -> str:
    """'train' or 'pretrain-pointmaps' for a training run that stopped before its first
    checkpoint (its config.yaml, maybe log.jsonl), told apart by the model section's keys; ""
    when config.yaml is not a training config."""
    try:
        text = (folder / "config.yaml").read_text(errors="replace")[:100_000]
    except OSError:
        return ""
    if not (re.search(r"^train:", text, re.M) and re.search(r"^\s+out_dir:", text, re.M)):
        return ""
    return "pretrain-pointmaps" if re.search(r"^\s+enc_embed_dim:", text, re.M) else "train"


def _export_kind(folder: Path) -> str | None:
    """'export-FORMAT' for a folder of `c4d export` scene folders (each holds c4d_export.json),
    directly or in its `scenes/` (the kubric export's layout)."""
    for record in [*folder.glob("*/c4d_export.json"), *folder.glob("scenes/*/c4d_export.json")]:
        try:
            fmt = json.loads(record.read_text()).get("format")
        except (OSError, ValueError, AttributeError):
            continue
        if isinstance(fmt, str) and f"export-{fmt}" in KINDS:
            return f"export-{fmt}"
    return None


# Folders written before markers existed: the first kind whose test passes (most specific first).
LEGACY_SIGNATURES: tuple[tuple[str, Callable[[Path], bool]], ...] = (
    ("demo", _has("demo-config.yaml")),
    ("datagen", _glob("dataset-*.json")),
    ("datagen", _glob("*-[0-9][0-9][0-9][0-9][0-9][0-9].tar")),
    ("run", _has("poses_tum.txt")),
    ("run", _has("report.json", "pointmaps.npz")),
    ("train", _has("checkpoints")),
    ("pretrain-pointmaps", _has("pointmap_net.pth")),
    ("pretrain-pointmaps", _has("last.pt", "config.yaml")),
    ("eval", _has("eval.json")),
    ("track", _has("tracks.npz")),
    ("inspect", _has("index.html")),
    ("inspect", _has("check.json")),
)


def read_marker(folder: Path) -> str | None:
    """The kind named by `folder`'s marker, or None when it has none (or an unreadable one)."""
    try:
        record = json.loads((folder / MARKER).read_text())
    except (OSError, ValueError):
        return None
    kind = record.get("kind") if isinstance(record, dict) else None
    return kind if isinstance(kind, str) and record.get("format") == FORMAT else None


def folder_kind(folder: str | os.PathLike) -> str | None:
    """Who made `folder`: a kind of `KINDS` (from its marker, else from the files of a folder
    written before markers), "" for a folder holding files c4d did not write, None for a folder
    that is missing or empty."""
    folder = Path(folder)
    if not folder.is_dir():
        return None
    marked = read_marker(folder)
    if marked is not None:
        return marked
    try:
        if not any(folder.iterdir()):
            return None
    except OSError:
        return None
    for kind, test in LEGACY_SIGNATURES:
        if test(folder):
            return kind
    if (folder / "config.yaml").is_file():
        return _config_kind(folder) or _export_kind(folder) or ""  # a training run stopped early?
    return _export_kind(folder) or ""


def _example(folder: Path) -> str:
    """A few entries of `folder`, for a message."""
    names = sorted(p.name for p in folder.iterdir())
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def _command(kind: str) -> str:
    """The command line that makes outputs of `kind` ('export-kubric' -> 'c4d export kubric')."""
    return "c4d " + kind.replace("export-", "export ")


def _describe(kind: str) -> str:
    return KINDS.get(kind, f"an output of `{_command(kind)}`")


def check_folder(path: str | os.PathLike, kind: str, overwrite: bool = False) -> str | None:
    """Refuse `path` as the output folder of `kind` unless it is new, empty, of that kind, or (with
    `overwrite`) made by another c4d command; returns the kind found (None: new or empty)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise UserError(f"the output {path} is a file, not a folder; give a folder (a new name)")
    found = folder_kind(path)
    if found == "":
        raise UserError(f"the output folder {path} holds files that c4d did not write "
                        f"({_example(path)}); give a new or empty folder (nothing there is "
                        "replaced, even with --overwrite)")
    if found not in (None, kind) and not overwrite:
        raise UserError(f"the output folder {path} is {_describe(found)}; `{_command(kind)}` does not "
                        "write into it: give another folder, or pass --overwrite to replace it "
                        "(the old folder is kept until the new output is complete)")
    return found


def mark_folder(path: Path, kind: str) -> None:
    """Write `path`'s marker naming `kind` (the folder is created)."""
    make_folder(path)
    if read_marker(path) != kind:
        write_json(path / MARKER, {"format": FORMAT, "kind": kind})


@contextlib.contextmanager
def output_folder(path: str | os.PathLike, kind: str, overwrite: bool = False) -> Iterator[Path]:
    """Claim `path` as the output folder of a `kind` command (`check_folder`), mark it, and yield it.

    With `overwrite` and a folder of another kind, that folder is renamed aside first; if the
    block fails (an error, Ctrl-C) the new output is removed and the old one put back, and when
    the block succeeds the old one is removed. A folder this call created and the block left
    with nothing but the marker is removed again on failure.
    """
    path = Path(path)
    found = check_folder(path, kind, overwrite)
    created = next((p for p in reversed((path, *path.parents)) if not p.exists()), None)
    aside = None
    if found not in (None, kind):
        aside = path.with_name(f".{path.name}.replaced{os.getpid()}")
        shutil.rmtree(aside, ignore_errors=True)
        os.replace(path, aside)
    try:
        mark_folder(path, kind)
        yield path
    except BaseException:
        if aside is not None:
            shutil.rmtree(path, ignore_errors=True)
            os.replace(aside, path)
        elif created is not None and path.is_dir() and [p.name for p in path.iterdir()] == [MARKER]:
            (path / MARKER).unlink()
            remove_empty_folders(created)
        raise
    if aside is not None:
        shutil.rmtree(aside, ignore_errors=True)


# --- single files -------------------------------------------------------------------------------


def _png_chunks(data: bytes) -> Iterator[tuple[bytes, bytes, int]]:
    """(type, data, end offset) of each chunk of the PNG `data` (after its 8-byte signature)."""
    pos = 8
    while pos + 8 <= len(data):
        (length,), ctype = struct.unpack(">I", data[pos:pos + 4]), data[pos + 4:pos + 8]
        end = pos + 12 + length
        yield ctype, data[pos + 8:pos + 8 + length], end
        pos = end


def mark_png(data: bytes, kind: str) -> bytes:
    """The PNG `data` with a `c4d-output` tEXt chunk naming `kind` after its header chunk."""
    if not data.startswith(b"\x89PNG\r\n\x1a\n"):
        raise ValueError("not a PNG")
    header_end = next(end for ctype, _, end in _png_chunks(data) if ctype == b"IHDR")
    body = b"tEXt" + PNG_KEYWORD + b"\0" + kind.encode("ascii")
    chunk = struct.pack(">I", len(body) - 4) + body + struct.pack(">I", zlib.crc32(body))
    return data[:header_end] + chunk + data[header_end:]


def html_marker(kind: str) -> str:
    """The tag a c4d HTML page carries in its head."""
    return f'<meta name="c4d-output" content="{kind}">'


def file_kind(path: str | os.PathLike) -> str | None:
    """The kind a c4d output file names inside it (JSON key, HTML meta tag, PNG text chunk), or
    None for any other file."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(1 << 20)
    except OSError:
        return None
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        for ctype, body, _ in _png_chunks(head):
            if ctype == b"tEXt" and body.startswith(PNG_KEYWORD + b"\0"):
                return body[len(PNG_KEYWORD) + 1:].decode("ascii", "replace")
            if ctype == b"IDAT":
                return None
        return None
    found = re.search(rb'<meta name="c4d-output" content="([a-z0-9-]+)">', head[:8192])
    if found:
        return found.group(1).decode("ascii")
    if b'<html lang="en" data-c4d-state=' in head[:200]:
        return "view"  # a page written before the tag
    if head.lstrip()[:1] == b"{":
        try:
            record = json.loads(path.read_bytes())
        except (OSError, ValueError):
            return None
        if not isinstance(record, dict):
            return None
        if JSON_KEY not in record and {"pred", "frame_indices"} <= record.keys():
            return "eval-recon"  # written before the key
        kind = record.get(JSON_KEY)
        return kind if isinstance(kind, str) else None
    return None


def check_file(path: str | os.PathLike, kind: str, overwrite: bool = False) -> Path:
    """Refuse `path` as the output file of a `kind` command unless it is new (outside a folder of
    another kind, but for `COMPANIONS`) or a file of that kind; with `overwrite` any regular file
    (and any folder's) is accepted, since the write replaces it atomically. Returns `path`."""
    path = Path(path)
    if path.is_dir():
        raise UserError(f"the output {path} is a folder; give a file name")
    if path.exists() and not path.is_file():
        raise UserError(f"the output {path} is not a regular file; give a file name")
    if overwrite:
        return path
    if path.exists():
        made = file_kind(path)
        if made != kind:
            what = f" (it is {_describe(made)})" if made else ""
            raise UserError(f"{path} exists and was not written by `{_command(kind)}`{what}; give "
                            "another file name, or pass --overwrite to replace it")
        return path
    parent = folder_kind(path.parent)
    if parent and parent != kind and path.name not in COMPANIONS.get((parent, kind), ()):
        raise UserError(f"{path.parent} is {_describe(parent)}; `{_command(kind)}` does not write "
                        "into it: give a file outside it, or pass --overwrite")
    return path


def write_png(path: str | os.PathLike, data: bytes, kind: str) -> Path:
    """Write the PNG `data` to `path` atomically, marked as an output of `kind`."""
    return write_bytes(path, mark_png(data, kind))
