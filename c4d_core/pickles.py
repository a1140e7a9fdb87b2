"""Reading pickles of arrays (TAP-Vid's benchmark files) without running code.

`pickle.load` builds whatever class a file names and calls whatever function it names, so a file
of unknown origin can run any command. The TAP-Vid pickles are dicts and lists of numpy arrays,
bytes (JPEG frames) and plain values; `read_data_pickle` unpickles with exactly the globals those
need (`ALLOWED_GLOBALS`: numpy's array and scalar reconstructors, `numpy.dtype`, and the bytes
decoder protocol-2 pickles use) and refuses any other in one line naming it.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

from c4d_core.errors import UserError

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


class _DataUnpickler(pickle.Unpickler):
    """An unpickler that resolves only `ALLOWED_GLOBALS`."""

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in ALLOWED_GLOBALS:
            raise pickle.UnpicklingError(f"refused global {module}.{name}")
        return super().find_class(module, name)


def read_data_pickle(path: str | os.PathLike, what: str, hint: str) -> Any:
    """The value pickled in `path`, built from arrays and plain values only.

    `what` names the file in messages ("TAP-Vid pickle"), `hint` says what to do instead. Raises
    `UserError` for a file that names any other class or function (it could run code), and for
    one that is unreadable, cut short or no pickle at all.
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            return _DataUnpickler(fh).load()
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
