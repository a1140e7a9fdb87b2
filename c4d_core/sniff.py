"""What a file is, from its first bytes: for messages that tell a user which file they passed.

A command given the wrong kind of file (a pickle where a shard is expected, an image where a
checkpoint is) says what the file is instead of calling it corrupt; `file_format` names the formats
users most often pass by mistake. Only signatures are read, never the whole file.
"""

from __future__ import annotations

import os
import zipfile

TAR, ZIP, PICKLE, EMPTY = "a tar archive", "a zip archive", "a Python pickle", "an empty file"
TORCH = "a PyTorch file (torch.save)"

# (offset, bytes there, what the file is), tried in order
_SIGNATURES: tuple[tuple[int, bytes, str], ...] = (
    (257, b"ustar", TAR),  # POSIX and GNU tar headers alike
    (0, b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (0, b"\xff\xd8\xff", "a JPEG image"),
    (0, b"GIF8", "a GIF image"),
    (0, b"\x93NUMPY", "a NumPy .npy array"),
    (4, b"ftyp", "an MP4/MOV video"),
    (0, b"\x1aE\xdf\xa3", "a Matroska/WebM video"),
    (0, b"\x1f\x8b\x08", "a gzip-compressed file"),
    (0, b"%PDF", "a PDF document"),
)
# torch.save's legacy (non-zip) layout: a pickle that starts with its magic number
_TORCH_LEGACY = b"\x80\x02\x8a\nl\xfc\x9cF\xf9 j\xa8P\x19"
_RIFF = {b"AVI ": "an AVI video", b"WEBP": "a WebP image", b"WAVE": "a WAV sound"}


def _zip_format(path: str | os.PathLike) -> str:
    """A zip archive by its member names: PyTorch's checkpoint layout, NumPy's .npz, or other."""
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
    except (OSError, zipfile.BadZipFile):
        return ZIP
    if any(name.endswith("/data.pkl") for name in names):
        return TORCH
    if names and all(name.endswith(".npy") for name in names):
        return "a NumPy .npz archive"
    return ZIP


def file_format(path: str | os.PathLike) -> str | None:
    """What the file at `path` is ("a Python pickle", "a PNG image", `TAR`, `EMPTY`,
    "a text file", ...), or None where no format known here matches (random or damaged bytes),
    it cannot be read or it is no regular file (a named pipe would wait for a writer)."""
    if not os.path.isfile(path):
        return None
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return None
    if not head:
        return EMPTY
    for offset, signature, name in _SIGNATURES:
        if head[offset:offset + len(signature)] == signature:
            return name
    if head.startswith(b"RIFF") and head[8:12] in _RIFF:
        return _RIFF[head[8:12]]
    if head.startswith(b"PK\x03\x04"):
        return _zip_format(path)
    if head.startswith(_TORCH_LEGACY):
        return TORCH
    if head[0] == 0x80 and 2 <= head[1] <= 5:  # the PROTO opcode of pickle protocols 2-5
        return PICKLE
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as exc:  # a multi-byte character cut at the end of `head` is text
        text = head[:exc.start].decode("utf-8") if exc.start >= len(head) - 3 else ""
    if not text or "\0" in text:
        return None
    return {"{": "a JSON file", "[": "a JSON file", "<": "an HTML/XML file"}.get(text.lstrip()[:1],
                                                                               "a text file")
