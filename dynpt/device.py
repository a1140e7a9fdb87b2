"""Device decisions as small pure functions, so the CUDA-only branches run (and are tested) on a CPU.

Each decision takes what it depends on (device type, bf16 support, free bytes) as arguments; only
`bf16_supported`, `free_memory`, the peak-memory pair and `device_for` (the GPU count for
`chosen_device`) ask the hardware. Callers: `dynpt.train` (process group backend, training
autocast, cuDNN flags), `dynpt.data` (pinned loader memory), `dynpt.inference` and
`c4d_pipeline.dust3r_pointmaps` (inference autocast, pair batch size from free memory), and every
device a user names, through `device_for` (`dynpt.inference.Tracker`, `c4d run`, the DUSt3R and
RAFT networks).
"""

from __future__ import annotations

import logging
from contextlib import nullcontext

import torch

from c4d_core.errors import UserError

log = logging.getLogger(__name__)


def bf16_supported(device: torch.device) -> bool:
    """Whether `device` runs bfloat16 natively (a CUDA GPU of compute capability >= 8.0)."""
    return device.type == "cuda" and torch.cuda.is_bf16_supported()


def free_memory(device: torch.device) -> int | None:
    """Free bytes on a CUDA `device`; None on a CPU (no budget to plan with)."""
    if device.type != "cuda":
        return None
    return int(torch.cuda.mem_get_info(device)[0])


def reset_peak_memory(device: torch.device) -> None:
    """Start a new peak-memory window on a CUDA `device` (nothing on a CPU)."""
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)


def peak_memory(device: torch.device) -> int | None:
    """Peak bytes allocated by tensors on a CUDA `device` since the last reset; None on a CPU."""
    if device.type != "cuda":
        return None
    return int(torch.cuda.max_memory_allocated(device))


def chosen_device(name: str | torch.device | None, gpus: int, torch_version: str) -> torch.device:
    """The device `name` names ('cpu', 'cuda', 'cuda:N'; None: 'cuda' where there is a GPU, else
    'cpu'), on a machine with `gpus` CUDA GPUs and torch `torch_version`. One-line `UserError`
    for a name torch does not know and for a GPU the machine lacks (a CPU-only torch build has
    none): asked for anyway, torch fails deep inside the first tensor moved there."""
    try:
        device = torch.device(name or ("cuda" if gpus else "cpu"))
    except RuntimeError as exc:
        raise UserError(f"unknown device {str(name)!r}; use cpu, cuda or cuda:N") from exc
    if device.type == "cuda" and not gpus:
        build = " (a CPU-only build)" if "+cpu" in torch_version else ""
        raise UserError(f"device {str(device)!r} requested but no CUDA GPU is available to torch "
                        f"{torch_version}{build}; use cpu")
    if device.type == "cuda" and (device.index or 0) >= gpus:
        raise UserError(f"device {str(device)!r} requested but this machine has {gpus} CUDA "
                        f"GPU(s), cuda:0 to cuda:{gpus - 1}; choose one of them or cpu")
    return device


def device_for(name: str | torch.device | None) -> torch.device:
    """`chosen_device` on this machine's GPUs: what every command's device setting goes through."""
    return chosen_device(name, torch.cuda.device_count() if torch.cuda.is_available() else 0,
                         torch.__version__)


def training_device(cuda_available: bool, local_rank: int) -> torch.device:
    """The device of one training process: its local GPU (`cuda:LOCAL_RANK`) or the CPU."""
    return torch.device(f"cuda:{local_rank}" if cuda_available else "cpu")


def ddp_backend(device_type: str) -> str:
    """torch.distributed backend: NCCL between GPUs, gloo between CPU processes."""
    return "nccl" if device_type == "cuda" else "gloo"


def ddp_device_ids(device: torch.device) -> list[int] | None:
    """DistributedDataParallel's `device_ids`: the process's one GPU, None for CPU modules."""
    return [device.index] if device.type == "cuda" else None


def pin_memory(device_type: str) -> bool:
    """Pin host batches (faster, asynchronous copies) only when they go to a GPU."""
    return device_type == "cuda"


def training_autocast_dtype(device_type: str, bf16: bool, supported: bool) -> torch.dtype | None:
    """Autocast dtype of training (`train.bf16`): bfloat16 on a GPU that has it, else None (fp32).

    float16 is never chosen: it would need loss scaling. A GPU without bf16 trains in fp32 (and
    says so once).
    """
    if device_type != "cuda" or not bf16:
        return None
    if not supported:
        log.warning("train.bf16: this GPU has no bfloat16; training in float32")
        return None
    return torch.bfloat16


def inference_autocast_dtype(device_type: str, supported: bool) -> torch.dtype | None:
    """Autocast dtype of the tracker's inference: bfloat16 (or float16 without it) on a GPU, None on
    a CPU (the pointmap network: `pointmap_autocast_dtype`)."""
    if device_type != "cuda":
        return None
    return torch.bfloat16 if supported else torch.float16


POINTMAP_PRECISIONS = ("fp32", "bf16")  # values of the config key pointmaps.precision


def pointmap_autocast_dtype(device_type: str, precision: str, supported: bool) -> torch.dtype | None:
    """Autocast dtype of the DUSt3R-family pointmap network (`pointmaps.precision`).

    'fp32' (the default, as the official inference): None. 'bf16': bfloat16 on a GPU (pointmaps
    move by about 1 % per pixel, docs/RESULTS.md section 5), None on a CPU. Another value, or
    'bf16' on a GPU without bfloat16, is a `UserError`.
    """
    if precision not in POINTMAP_PRECISIONS:
        raise UserError(f"pointmaps.precision must be one of {', '.join(POINTMAP_PRECISIONS)}, "
                        f"got {precision!r}")
    if precision == "fp32" or device_type != "cuda":
        return None
    if not supported:
        raise UserError("this GPU has no bfloat16 support; use pointmaps.precision=fp32")
    return torch.bfloat16


def autocast(device_type: str, dtype: torch.dtype | None):
    """`torch.autocast(device_type, dtype)`, or a no-op context for dtype None."""
    return torch.autocast(device_type, dtype=dtype) if dtype is not None else nullcontext()


def cudnn_flags(device_type: str) -> dict[str, bool]:
    """Settings of `torch.backends.cudnn` for training: benchmark mode (the crop size is fixed,
    so the fastest convolution algorithm is searched once per shape); none on a CPU."""
    return {"benchmark": True} if device_type == "cuda" else {}


def apply_cudnn_flags(flags: dict[str, bool]) -> None:
    """Set `torch.backends.cudnn.<name> = value`; a name cuDNN does not have is an error."""
    for name, value in flags.items():
        if not hasattr(torch.backends.cudnn, name):
            raise AttributeError(f"torch.backends.cudnn has no setting {name!r}")
        setattr(torch.backends.cudnn, name, value)


def pair_batch_size(free_bytes: int | None, weight_bytes: int, pair_bytes: int,
                    cpu_batch: int = 2, max_batch: int = 64) -> int:
    """Image pairs per forward pass: `cpu_batch` without a memory budget (CPU), else as many pairs
    of `pair_bytes` activations as fit in 70 % of `free_bytes` less a tenth of the weights'
    bytes (working copies), clipped to [1, max_batch]."""
    if free_bytes is None:
        return cpu_batch
    budget = 0.7 * free_bytes - 0.1 * weight_bytes
    return int(min(max(budget // max(pair_bytes, 1), 1), max_batch))
