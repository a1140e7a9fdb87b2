"""Reading official DUSt3R / MASt3R / MonST3R checkpoint files without executing their code.

An official file (croco's `save_model`) is a pickled dict `{'model': state_dict, 'args':
argparse.Namespace, ...}` whose `args.model` is the network's constructor call as a string, e.g.
"AsymmetricCroCo3DStereo(pos_embed='RoPE100', img_size=(512, 512), head_type='dpt', ...,
depth_mode=('exp', -inf, inf), conf_mode=('exp', 1, inf), enc_embed_dim=1024, ...)". The upstream
code `eval`s that string; here it is parsed with `ast` into a name and a dict of literal keyword
values, and anything that is not a literal (a call, an attribute, an expression) is refused.

Security: a file a user names is data, never code. The `argparse.Namespace` of these files is the
only Python object beyond tensors and plain values they need, so `read_checkpoint` reads them with
`torch.load(weights_only=True)` and exactly that class allowed (`ALLOWED_GLOBALS`). A file holding
anything else (a class that could run code when built) is refused in one line that says how to
turn a file you trust into a plain one (`CONVERT_HINT`); the full unpickler is never used.

A folder or a missing path, and why `torch.load` failed, are named as every reader of the project
names them (`dynpt.torch_files`). A training state of `c4d pretrain-pointmaps` (`last.pt`) is
refused, naming the network file its run writes (`pointmap_net.pth`), rather than read as bare
weights of guessed sizes.
"""

from __future__ import annotations

import argparse
import ast
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from c4d_core.errors import UserError
from dynpt.torch_files import holds_objects, load_failure, require_file

# Bare names the constructor strings use for numbers (`inf` comes from `from numpy import inf`).
_NAMED_CONSTANTS = {"inf": math.inf, "nan": math.nan, "True": True, "False": False, "None": None}


@dataclass(frozen=True)
class OfficialCheckpoint:
    """The parts of an official checkpoint file this project uses.

    `state_dict` maps parameter names (any leading `module.` removed) to tensors; `constructor` is
    the class name of `args.model` (empty if the file has no args) and `kwargs` its keyword values.
    """

    path: Path
    state_dict: dict[str, torch.Tensor]
    constructor: str = ""
    kwargs: dict[str, Any] = field(default_factory=dict)


def _literal(node: ast.AST, text: str) -> Any:
    """The Python value of one literal node of a constructor string; refuses everything else."""
    if isinstance(node, ast.Constant):
        return node.value
    if isinstance(node, ast.Name) and node.id in _NAMED_CONSTANTS:
        return _NAMED_CONSTANTS[node.id]
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        value = _literal(node.operand, text)
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            return -value if isinstance(node.op, ast.USub) else value
    if isinstance(node, (ast.Tuple, ast.List)):
        values = [_literal(item, text) for item in node.elts]
        return tuple(values) if isinstance(node, ast.Tuple) else values
    if isinstance(node, ast.Dict) and all(key is not None for key in node.keys):
        return {_literal(k, text): _literal(v, text) for k, v in zip(node.keys, node.values)}
    # float('inf') and friends, the only call allowed inside a value.
    if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "float"
            and len(node.args) == 1 and not node.keywords):
        value = _literal(node.args[0], text)
        if isinstance(value, (str, int, float)):
            return float(value)
    raise ValueError(f"not a literal value: {ast.get_source_segment(text, node) or ast.dump(node)}")


def parse_constructor(text: str) -> tuple[str, dict[str, Any]]:
    """Parse "Name(key=literal, ...)" into ("Name", {key: value}) without evaluating anything.

    Values may be numbers, strings, booleans, None, `inf`/`-inf`, `float('inf')`, and tuples,
    lists or dicts of those. Raises `ValueError` for any other construct or for positional args.
    """
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise ValueError(f"constructor string is not valid Python syntax: {exc.msg}") from exc
    call = tree.body
    if not (isinstance(call, ast.Call) and isinstance(call.func, ast.Name)):
        raise ValueError("constructor string is not of the form Name(key=value, ...)")
    if call.args:
        raise ValueError("constructor string has positional arguments; only key=value is supported")
    kwargs = {}
    for keyword in call.keywords:
        if keyword.arg is None:
            raise ValueError("constructor string uses **kwargs, which is not supported")
        kwargs[keyword.arg] = _literal(keyword.value, text)
    return call.func.id, kwargs


# The numpy dtype classes of plain values (numbers, booleans, text); not object or void.
_PLAIN_DTYPES = tuple(type(np.dtype(code)) for code in "?bhilqBHILQefdgFDGUS")

# The globals an official DUSt3R / MASt3R / MonST3R file needs: its training arguments, and the
# numpy scalars croco's `save_model` may store beside them (a `best_so_far` float, numpy-string
# parameter names): `numpy.core.multiarray.scalar` builds one from its dtype and raw bytes and
# calls nothing else.
_NUMPY_SCALAR = np.float64(0).__reduce__()[0]  # numpy.(_)core.multiarray.scalar
ALLOWED_GLOBALS = (argparse.Namespace, np.dtype, *_PLAIN_DTYPES,
                   (_NUMPY_SCALAR, "numpy.core.multiarray.scalar"),  # as numpy 1.x names it
                   (_NUMPY_SCALAR, "numpy._core.multiarray.scalar"))  # and 2.x

# How to turn a trusted file with other Python objects into one this loader reads: its weights and
# its arguments as a plain dict (`args.model` is read from a dict as from a Namespace).
CONVERT_HINT = ("if you trust the file, convert it once: python -c \"import sys, torch; "
                "c = torch.load(sys.argv[1], weights_only=False); "
                "torch.save({'model': c['model'], 'args': vars(c['args'])}, sys.argv[2])\" IN OUT")


def _torch_load(path: Path, map_location: Any) -> Any:
    """`torch.load` in tensor-only mode with `ALLOWED_GLOBALS` allowed; nothing else is built."""
    with torch.serialization.safe_globals(list(ALLOWED_GLOBALS)):
        return torch.load(path, map_location=map_location, weights_only=True)


# `c4d pretrain-pointmaps` saves its training state (`last.pt`, for --resume) as the network's
# weights under 'model' with these beside them and no 'args'; read as a bare state dict it would
# run with guessed sizes (512 pixels), so it is refused, naming the run's network file instead.
TRAINING_STATE_KEYS = frozenset({"optimizer", "schedule", "step"})
PRETRAINED_NETWORK = "pointmap_net.pth"  # the network file beside it, written when the run ends


def _refuse_training_state(path: Path) -> None:
    """The `UserError` for a `c4d pretrain-pointmaps` training state passed as a network."""
    network = path.parent / PRETRAINED_NETWORK
    fix = (f"pass {network}, the network that run wrote" if network.is_file() else
           f"its run has not finished (no {network} yet): continue it with `c4d pretrain-pointmaps "
           "--resume`, which writes that network file")
    raise UserError(f"{path} is a training state of `c4d pretrain-pointmaps` (for --resume), not "
                    f"a pointmap network; {fix}")


def _constructor_string(args: Any) -> str:
    """`args.model` of an official checkpoint (Namespace, dict or the string itself)."""
    if isinstance(args, str):
        return args
    if isinstance(args, dict):
        return str(args.get("model", ""))
    return str(getattr(args, "model", "") or "")


def read_checkpoint(path: str | Path, map_location: Any = "cpu") -> OfficialCheckpoint:
    """Read an official DUSt3R-family checkpoint (or a bare state dict) from a local file.

    Raises `UserError` if the file is missing, unreadable, not a checkpoint, or its constructor
    string cannot be parsed safely.
    """
    path = Path(path)
    require_file(path, "checkpoint file", "pass the path of a downloaded DUSt3R/MASt3R/MonST3R "
                 ".pth file")
    try:
        ckpt = _torch_load(path, map_location)
    except Exception as exc:  # a damaged file can fail anywhere inside the unpickler
        hint = CONVERT_HINT if holds_objects(exc) else "download it again or pass another file"
        raise UserError(f"cannot read checkpoint {str(path)!r} ({load_failure(exc, path)}); "
                        f"{hint}") from exc
    if not isinstance(ckpt, dict):
        raise UserError(f"{str(path)!r} is not a checkpoint (a dict with 'model' and 'args'); pass an "
                        "official DUSt3R/MASt3R/MonST3R .pth file")
    if "args" not in ckpt and TRAINING_STATE_KEYS <= ckpt.keys():
        _refuse_training_state(path)
    state = ckpt["model"] if "model" in ckpt and isinstance(ckpt["model"], dict) else ckpt
    state = {k.removeprefix("module."): v for k, v in state.items() if isinstance(v, torch.Tensor)}
    if not state:
        raise UserError(f"{str(path)!r} contains no weights; pass an official DUSt3R/MASt3R/MonST3R "
                        ".pth file")
    text = _constructor_string(ckpt.get("args", "")) if "model" in ckpt else ""
    name, kwargs = "", {}
    if text:
        try:
            name, kwargs = parse_constructor(text)
        except ValueError as exc:
            raise UserError(f"cannot parse the network description args.model of {str(path)!r}: "
                            f"{exc}; the file is not an official checkpoint") from exc
    return OfficialCheckpoint(path=path, state_dict=state, constructor=name, kwargs=kwargs)


def rope_frequency(kwargs: dict[str, Any], default: float = 100.0) -> float:
    """RoPE base from `pos_embed='RoPE100'`; `default` if absent. Cosine embeddings are refused."""
    pos_embed = str(kwargs.get("pos_embed", f"RoPE{default:g}"))
    if not pos_embed.startswith("RoPE"):
        raise UserError(f"checkpoint uses pos_embed={pos_embed!r}; only RoPE checkpoints "
                        "(pos_embed='RoPE100', all released DUSt3R/MASt3R/MonST3R files) are supported")
    return float(pos_embed[len("RoPE"):] or default)


# CroCoNet's defaults, which the official code gets when args.model omits the head counts (it
# evaluates the string, so the constructor defaults apply, whatever the width).
CROCO_DEFAULT_HEADS = {"enc_num_heads": 12, "dec_num_heads": 16}


def head_count(ckpt: OfficialCheckpoint, name: str, width: int) -> int:
    """Attention heads `name` ('enc_num_heads' or 'dec_num_heads') of a network `width` wide.

    The value in args.model if given; CroCo's default (12 encoder, 16 decoder heads) when the file
    has args.model without it, as the official code builds it; width / 64 (the released ViT-L/B
    ratio) for a bare state dict, which has no description at all. Raises `UserError` if the
    width does not split into that many heads of a multiple of 4 channels (2-D RoPE needs it).
    """
    if name in ckpt.kwargs:
        heads = int(ckpt.kwargs[name])
    elif ckpt.constructor:
        heads = CROCO_DEFAULT_HEADS[name]
    else:
        heads = max(1, width // 64)
    if heads < 1 or width % heads or (width // heads) % 4:
        where = "its args.model" + ("" if name in ckpt.kwargs else f" (no {name}: CroCo's default)")
        raise UserError(f"{str(ckpt.path)!r}: width {width} does not split into {heads} attention heads "
                        f"with a channel count divisible by 4, as {where} says; the file's description "
                        "does not match its weights")
    return heads


def block_count(state_dict: dict[str, torch.Tensor], prefix: str) -> int:
    """Number of blocks `prefix{i}.` present in a state dict (max index + 1; 0 if none)."""
    indices = {int(k[len(prefix):].split(".", 1)[0]) for k in state_dict if k.startswith(prefix)}
    return max(indices) + 1 if indices else 0
