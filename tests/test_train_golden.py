"""A fixed, seeded training step (forward, loss, backward) gives the loss terms and gradients of
the code before the training-speed work of issue 29, to rounding.

tests/fixtures/train_step_golden.npz was written by `python tests/test_train_golden.py --write`
from that earlier code (commit 5e71ef8's model, as 1e98435's); an optimisation of the model, the correlation, the
transformer or the losses must leave these numbers as they are. Per case it holds the weighted
loss terms and, per trainable tensor, the gradient's sum, its L2 norm and 16 of its entries at
seeded positions. Weights are `tests.golden.seeded_state`'s rule over the parameter names (not
torch's initialisation, so a change in how modules are built cannot move them).

The step runs in a child process whose CPU kernels are pinned to their AVX2 code paths (`PINNED`:
ATen's vectorised kernels, oneDNN's convolutions, MKL's matrix products) on one thread. The
rounding of a convolution's or a product's sums depends on the instruction set a library picks,
and a training step amplifies it past these tolerances: the golden written on an AVX-512 machine
failed on an AVX2 one (AMD EPYC, 2026-12-06), with the earlier code itself. AVX2 is on every
x86-64 machine this runs on; the golden was rewritten pinned so (the earlier code's numbers and
today's agree there).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from c4d_core.config import load_config
from dynpt.losses import LossWeights, dynpt_loss
from dynpt.model import build_model

GOLDEN = Path(__file__).resolve().parent / "fixtures" / "train_step_golden.npz"
SAMPLES = 16  # gradient entries stored per tensor
PINNED = {"ATEN_CPU_CAPABILITY": "avx2", "ONEDNN_MAX_CPU_ISA": "AVX2", "MKL_CBWR": "AVX2",
          "OMP_NUM_THREADS": "1"}  # read as torch loads: set in a child process
ROOT = Path(__file__).resolve().parents[1]

TINY_3E = ["model.encoder_3d.random_init=true"]
CT3_OFFLINE = ["model.windowing=cotracker3_offline", "model.time_embedding=cotracker3",
               "model.time_emb_len=10", "model.sampling=cotracker3"]
CT3_ONLINE = ["model.windowing=cotracker3_online", "model.time_embedding=cotracker3",
              "model.time_emb_len=8", "model.sampling=cotracker3"]
# name -> (preset, overrides, (B, T, H, W, N)); tiny's window is 8 frames moved by 4
CASES = {
    "tiny-causal-2-windows": ("tiny-cpu", [], (2, 12, 64, 64, 16)),
    "tiny-3d-encoder": ("tiny-cpu", TINY_3E, (1, 8, 64, 64, 12)),
    "tiny-cotracker3-offline": ("tiny-cpu", CT3_OFFLINE, (1, 10, 48, 64, 12)),
    "tiny-cotracker3-online": ("tiny-cpu", CT3_ONLINE, (1, 12, 64, 48, 12)),
    "cnn-only-released-sizes": ("paper-gpu-cnn-only", ["model.train_iters=2"], (1, 6, 64, 64, 8)),
}


def seeded_model(preset: str, overrides: list[str]):
    """The case's model in training mode, every parameter from the seeded rule; its loss weights."""
    from tests.golden import seeded_state

    cfg = load_config("dynpt", preset, overrides=overrides)
    model = build_model(cfg.model).train()
    params = list(model.named_parameters())  # the frozen 3D encoder's too
    state = seeded_state([k for k, _ in params], [tuple(p.shape) for _, p in params],
                         [""] * len(params), ["torch.float32"] * len(params), seed=29)
    model.load_state_dict(state, strict=False)
    return model, LossWeights.from_config(cfg.loss)


def seeded_batch(B: int, T: int, H: int, W: int, N: int):
    """video (B,T,3,H,W) 0..255, queries (B,N,3), and targets: a random walk from each query,
    visible at the query frame, ~20 % moving."""
    g = torch.Generator().manual_seed(7)
    video = (torch.rand(B, T, 3, H, W, generator=g) * 255).round()
    t_q = torch.randint(0, T // 2, (B, N), generator=g)
    xy_q = torch.rand(B, N, 2, generator=g) * torch.tensor([W - 1.0, H - 1.0])
    steps = torch.randn(B, T, N, 2, generator=g) * 1.5
    walk = steps.cumsum(1) - steps.cumsum(1).gather(1, t_q[:, None, :, None].expand(B, 1, N, 2))
    tracks = xy_q[:, None] + walk
    frames = torch.arange(T)[None, :, None]
    visible = (torch.rand(B, T, N, generator=g) > 0.25) | (frames == t_q[:, None])
    moving = torch.rand(B, T, N, generator=g) > 0.8
    queries = torch.cat([t_q[..., None].float(), xy_q], dim=-1)
    return video, queries, {"tracks": tracks, "visible": visible, "moving": moving}


def step_numbers(name: str) -> dict[str, np.ndarray]:
    """One forward + loss + backward of the case: its loss terms and gradient statistics."""
    preset, overrides, size = CASES[name]
    model, weights = seeded_model(preset, overrides)
    video, queries, target = seeded_batch(*size)
    loss, terms = dynpt_loss(model(video, queries), target, weights)
    loss.backward()
    out = {f"{name}/terms": np.array([float(v.detach()) for v in (loss, *terms.values())])}
    rng = np.random.default_rng(0)
    for key, p in model.named_parameters():
        if not p.requires_grad:
            continue
        grad = p.grad.detach().double().flatten().numpy()
        picks = rng.integers(0, grad.size, SAMPLES)
        out[f"{name}/grad/{key}"] = np.concatenate([[grad.sum(), np.linalg.norm(grad)], grad[picks]])
    return out


def pinned_numbers(out: Path) -> None:
    """Every case's `step_numbers`, computed in a child process with the `PINNED` kernels, saved
    to `out` (.npz)."""
    env = {**os.environ, **PINNED, "PYTHONPATH": f"{ROOT}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    subprocess.run([sys.executable, __file__, "--numbers", str(out)], env=env, check=True,
                   timeout=600)


@pytest.fixture(scope="module")
def actual_numbers():
    with tempfile.TemporaryDirectory() as folder:
        pinned_numbers(Path(folder) / "numbers.npz")
        with np.load(Path(folder) / "numbers.npz") as data:
            yield {k: data[k] for k in data.files}


@pytest.mark.parametrize("name", list(CASES))
def test_training_step_matches_the_earlier_code(name, actual_numbers):
    with np.load(GOLDEN) as data:
        expected = {k: data[k] for k in data.files if k.startswith(f"{name}/")}
    actual = {k: v for k, v in actual_numbers.items() if k.startswith(f"{name}/")}
    assert sorted(actual) == sorted(expected)
    np.testing.assert_allclose(actual[f"{name}/terms"], expected[f"{name}/terms"], rtol=2e-5, atol=1e-7)
    grads = [key for key in expected if "/grad/" in key]
    largest = max(expected[key][1] for key in grads)  # the largest gradient norm of the step
    for key in grads:
        # to rounding: of the tensor's own size, and of the step's (the biases before an instance
        # norm have a gradient of zero in exact arithmetic, i.e. rounding noise of ~1e-9 of it)
        atol = 1e-5 * expected[key][1] + 2e-6 * largest
        np.testing.assert_allclose(actual[key], expected[key], rtol=1e-4, atol=atol, err_msg=key)


if __name__ == "__main__" and sys.argv[1:2] == ["--numbers"]:  # the child of `pinned_numbers`
    torch.set_num_threads(1)
    numbers: dict[str, np.ndarray] = {}
    for case in CASES:
        numbers.update(step_numbers(case))
    np.savez_compressed(sys.argv[2], **numbers)
elif __name__ == "__main__" and sys.argv[1:] == ["--write"]:
    pinned_numbers(GOLDEN)
    print(f"wrote {GOLDEN}")
