"""Reading pickles of arrays (TAP-Vid's benchmark files) without running code.

`pickle.load` builds whatever class a file names and calls whatever function it names, so a file
of unknown origin can run any command. The TAP-Vid pickles are dicts and lists of numpy arrays,
bytes (JPEG frames) and plain values; `read_data_pickle` unpickles with exactly the globals those
need (`ALLOWED_GLOBALS`: numpy's array and scalar reconstructors, `numpy.dtype`, and the bytes
decoder protocol-2 pickles use) and refuses any other in one line naming it.

Allowed calls can still ask for memory: `_reconstruct(ndarray, shape, dtype)` allocates `shape`
at once, and a file naming a 10^13-element shape is 9 TiB of it. numpy itself always pickles an
array as `_reconstruct(ndarray, (0,), ...)`, then fills it with bytes the file carries (its
`__setstate__` checks their length), so an honest array is never larger than the file holding it:
a reconstruct call asking for more bytes than the file has is refused before allocating. A file
that names one bytes object many times (the pickle memo) gets arrays that share it: numpy views
the bytes of a pickled array instead of copying them.

`np.save` of a dict (CoTracker's Kubric annotations) is a `.npy` file whose array is a pickled 0-d
object array: `read_data_pickle(..., npy=True)` reads its header as text (numpy's header parser,
a literal evaluator) and the pickle after it with the same restricted unpickler.
"""

from __future__ import annotations

import math
import os
import pickle
from pathlib import Path
from typing import Any, Callable

import numpy as np

from c4d_core.errors import UserError
from c4d_core.files import check_regular_file
from c4d_core.system import gib

# (module, name) -> why it is safe: each builds a value from plain data and calls nothing else.
ALLOWED_GLOBALS = frozenset({
    ("numpy", "ndarray"),  # the class `_reconstruct` is given; it only allocates
    ("numpy", "dtype"),
    ("numpy.core.multiarray", "_reconstruct"),  # numpy 1.x pickles
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),  # numpy 2.x pickles
    ("numpy._core.multiarray", "scalar"),
    ("numpy.core.numeric", "_frombuffer"),  # protocol-5 pickles of arrays
    ("numpy._core.numeric", "_frombuffer"),
    ("_codecs", "encode"),  # bytes in protocol-2 pickles: encode(text, 'latin1')
})


class _TooLarge(pickle.UnpicklingError):
    """An array reconstructor call asking for more bytes than the whole file holds."""


def _bounded(reconstruct: Callable, limit: int) -> Callable:
    """numpy's `_reconstruct(subtype, shape, dtype)`, refusing (`_TooLarge`) a shape of more than
    `limit` bytes before anything is allocated."""

    def build(subtype, shape, dtype):
        dims = shape if isinstance(shape, (tuple, list)) else (shape,)
        size = math.prod(int(n) for n in dims) * np.dtype(dtype).itemsize
        if size > limit:
            raise _TooLarge(f"an array of shape {tuple(dims)} and dtype {np.dtype(dtype)} "
                            f"({gib(size)})")
        return reconstruct(subtype, shape, dtype)

    return build


class _DataUnpickler(pickle.Unpickler):
    """An unpickler that resolves only `ALLOWED_GLOBALS`, whose array reconstructors build no
    array of more than `limit` bytes."""

    def __init__(self, file, limit: int):
        super().__init__(file)
        self.limit = limit

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"refused global {module}.{name}")
        found = super().find_class(module, name)
        return _bounded(found, self.limit) if name == "_reconstruct" else found


def _skip_npy_header(fh) -> None:
    """Read past the header of the `.npy` file `fh`, which must hold a pickled object array (what
    `np.save` writes for a dict); `pickle.UnpicklingError` for a file of plain numbers (no pickle)
    and ValueError for a damaged header."""
    version = np.lib.format.read_magic(fh)
    if version not in ((1, 0), (2, 0)):
        raise ValueError(f".npy format version {version}")
    read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                   else np.lib.format.read_array_header_2_0)
    _, _, dtype = read_header(fh)
    if not dtype.hasobject:
        raise pickle.UnpicklingError(f"an .npy file of {dtype} numbers, no pickled object")


def read_data_pickle(path: str | os.PathLike, what: str, hint: str, npy: bool = False) -> Any:
    """The value pickled in `path`, built from arrays and plain values only.

    `what` names the file in messages ("TAP-Vid pickle"), `hint` says what to do instead. `npy`:
    the file is an `.npy` file of pickled objects (`np.save` of a dict); its header is skipped and
    the value returned is the pickled object array (a dict's is 0-d: `.item()` gives the dict).
    Raises `UserError` for a file that names any other class or function (it could run code), and
    for one that is unreadable, cut short or no pickle at all, and for a path that is no regular
    file (a named pipe, a device), before opening it.
    """
    path = check_regular_file(path, what, hint)
    try:
        with open(path, "rb") as fh:
            if npy:
                _skip_npy_header(fh)
            return _DataUnpickler(fh, os.fstat(fh.fileno()).st_size).load()
    except _TooLarge as exc:
        raise UserError(f"{what} {str(path)!r} asks for {exc}, more than its "
                        f"{os.path.getsize(path)} bytes can carry: it is damaged or was not "
                        f"written by numpy, and was not read; {hint}") from exc
    except pickle.UnpicklingError as exc:
        if str(exc).startswith("refused global"):
            raise UserError(f"{what} {str(path)!r} holds Python objects other than arrays and plain "
                            f"values ({str(exc).removeprefix('refused global ')}), which could run "
                            f"code, and was not read; {hint}") from exc
        raise UserError(f"cannot read {str(path)!r} as a {what} (not a pickle, or damaged); "
                        f"{hint}") from exc
    except (EOFError, ValueError, TypeError, AttributeError, IndexError, KeyError) as exc:
        raise UserError(f"cannot read {str(path)!r} as a {what} (cut short or damaged); {hint}") from exc
    except OSError as exc:
        raise UserError(f"cannot read {str(path)!r}: {exc.strerror or exc}; {hint}") from exc
