"""The CUDA-only branches, run on a CPU: each decision of dynpt/device.py is forced with a fake
capability or memory budget, and the code that acts on it runs for real where a CPU can (bf16
autocast exists on the CPU too), so a typo there fails here rather than on a user's first GPU."""

import numpy as np
import pytest
import torch
import torch.distributed as dist

from c4d_core.config import load_config
from c4d_core.errors import UserError
from c4d_pipeline.dust3r_pointmaps import Dust3rPointmaps, pair_memory_bytes
from dynpt import device as dev
from dynpt import train as train_module
from dynpt.data import ShardStream, make_loader
from dynpt.dust3r.net import Dust3rConfig, Dust3rNet
from dynpt.inference import Tracker
from dynpt.model import build_model
from tests.dynpt_testdata import synthetic_shards

GPU = torch.device("cuda:1")
TINY_NET = Dust3rConfig(enc_embed_dim=32, enc_depth=1, enc_num_heads=2, dec_embed_dim=32, dec_depth=2,
                        dec_num_heads=2, dpt_layer_dims=(8, 8, 16, 16), dpt_feature_dim=16,
                        dpt_last_dim=8)


def test_backend_device_and_pinning_choices():
    assert dist.Backend(dev.ddp_backend("cuda")) == dist.Backend.NCCL  # Backend() rejects a typo
    assert dist.Backend(dev.ddp_backend("cpu")) == dist.Backend.GLOO
    assert dev.training_device(True, 3) == torch.device("cuda", 3)
    assert dev.training_device(False, 3) == torch.device("cpu")
    assert dev.ddp_device_ids(GPU) == [1] and dev.ddp_device_ids(torch.device("cpu")) is None
    assert dev.pin_memory("cuda") and not dev.pin_memory("cpu")
    stream = ShardStream([synthetic_shards(4, 2)], [1.0], load_config("dynpt", "tiny-cpu").data, 0)
    assert make_loader(stream, 2, 0, "cuda").pin_memory
    assert not make_loader(stream, 2, 0, "cpu").pin_memory


def test_autocast_dtypes():
    assert dev.training_autocast_dtype("cuda", True, True) is torch.bfloat16
    assert dev.training_autocast_dtype("cuda", True, False) is None  # never fp16 without scaling
    assert dev.training_autocast_dtype("cuda", False, True) is None
    assert dev.training_autocast_dtype("cpu", True, True) is None
    assert dev.inference_autocast_dtype("cuda", True) is torch.bfloat16
    assert dev.inference_autocast_dtype("cuda", False) is torch.float16
    assert dev.inference_autocast_dtype("cpu", True) is None
    assert dev.pointmap_autocast_dtype("cuda", "fp32", True) is None  # the official inference's fp32
    assert dev.pointmap_autocast_dtype("cuda", "bf16", True) is torch.bfloat16
    assert dev.pointmap_autocast_dtype("cpu", "bf16", True) is None
    with pytest.raises(UserError, match="no bfloat16"):
        dev.pointmap_autocast_dtype("cuda", "bf16", False)


def test_hardware_queries_call_the_cuda_api(monkeypatch):
    """The only functions that ask the GPU, with torch.cuda faked: names and units are right."""
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda d: (5 * 2**30, 80 * 2**30))
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda d: 3 * 2**30)
    reset = []
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", reset.append)
    assert dev.bf16_supported(GPU) and not dev.bf16_supported(torch.device("cpu"))
    assert dev.free_memory(GPU) == 5 * 2**30 and dev.free_memory(torch.device("cpu")) is None
    assert dev.peak_memory(GPU) == 3 * 2**30 and dev.peak_memory(torch.device("cpu")) is None
    dev.reset_peak_memory(GPU)
    dev.reset_peak_memory(torch.device("cpu"))
    assert reset == [GPU]


def test_cudnn_flags_are_real_settings():
    before = torch.backends.cudnn.benchmark
    try:
        dev.apply_cudnn_flags(dev.cudnn_flags("cuda"))
        assert torch.backends.cudnn.benchmark is True
    finally:
        torch.backends.cudnn.benchmark = before
    assert dev.cudnn_flags("cpu") == {}
    with pytest.raises(AttributeError, match="benchmarc"):
        dev.apply_cudnn_flags({"benchmarc": True})


def test_init_distributed_on_a_fake_gpu_node(monkeypatch):
    """torchrun's environment with CUDA faked: local GPU, cuDNN flags, NCCL process group."""
    calls = {}
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "set_device", lambda d: calls.setdefault("device", d))
    monkeypatch.setattr(dist, "is_initialized", lambda: False)
    monkeypatch.setattr(dist, "init_process_group", lambda backend: calls.setdefault("backend", backend))
    monkeypatch.setattr(dist, "get_rank", lambda: 3)
    monkeypatch.setattr(train_module, "apply_cudnn_flags", lambda f: calls.setdefault("cudnn", f))
    assert train_module.init_distributed() == (3, 4, GPU)
    assert calls == {"device": GPU, "cudnn": {"benchmark": True}, "backend": "nccl"}


@pytest.mark.parametrize("encoder", [[], ["model.encoder_3d.random_init=true"]], ids=["ce", "ce+3e"])
def test_a_training_step_under_bf16_autocast(encoder):
    """The tiny model trains one step under bfloat16 autocast (the CUDA branch's dtype, on the CPU)."""
    torch.manual_seed(0)
    model = build_model(load_config("dynpt", "tiny-cpu", overrides=encoder).model)
    video = torch.randint(0, 255, (1, 6, 3, 32, 32)).float()
    queries = torch.tensor([[[0.0, 10.0, 12.0], [2.0, 20.0, 5.0]]])
    with dev.autocast("cpu", torch.bfloat16):
        out = model(video, queries)
    loss = sum(t.float().square().mean() for t in (out.coords[-1], out.vis_logits[-1], out.moving_logits[-1]))
    loss.backward()
    assert torch.isfinite(loss)
    assert all(p.grad is None or torch.isfinite(p.grad).all() for p in model.parameters())


def test_tracker_and_pointmaps_under_autocast(monkeypatch):
    """The inference branches' autocast with a forced dtype: finite float32 outputs."""
    model = build_model(load_config("dynpt", "tiny-cpu").model)
    tracker = Tracker(model, "cpu")
    monkeypatch.setattr("dynpt.inference.inference_autocast_dtype", lambda t, s: torch.bfloat16)
    with tracker._autocast():
        assert torch.get_autocast_dtype("cpu") is torch.bfloat16 and torch.is_autocast_enabled("cpu")
    video = np.random.default_rng(0).integers(0, 256, (10, 32, 32, 3), dtype=np.uint8)
    result = tracker.track(video, np.array([[0, 5.0, 6.0], [4, 20.0, 11.0]]))  # both directions
    assert result.tracks.dtype == np.float32 and np.isfinite(result.tracks).all()
    torch.manual_seed(0)
    source = Dust3rPointmaps(Dust3rNet(TINY_NET), device="cpu", batch_size=2)
    source.amp_dtype = torch.bfloat16
    frames = np.random.default_rng(0).integers(0, 256, (3, 32, 48, 3), dtype=np.uint8)
    pw = source.pointmaps(frames, np.array([[0, 1], [1, 2], [2, 0]]))
    assert pw.pts_i.dtype == np.float32 and np.isfinite(pw.pts_i).all() and (pw.conf_i >= 1).all()


def test_pair_batch_size_from_a_memory_budget(monkeypatch):
    assert dev.pair_batch_size(None, 10, 10) == 2  # CPU: fixed
    assert dev.pair_batch_size(100 * 2**20, 0, 7 * 2**20) == 10  # 70 MiB / 7 MiB
    assert dev.pair_batch_size(100 * 2**20, 200 * 2**20, 7 * 2**20) == 7  # weights' share
    assert dev.pair_batch_size(2**20, 0, 2**30) == 1 and dev.pair_batch_size(2**40, 0, 1) == 64
    net = Dust3rNet(TINY_NET)
    source = Dust3rPointmaps(net, device="cpu")
    assert source._auto_batch(32, 48) == 2
    pair = pair_memory_bytes(net, 32, 48)
    weights = sum(p.numel() * p.element_size() for p in net.parameters())
    free = 10 * pair + weights // 7 + 8  # 70 % of it, less a tenth of the weights: 7 pairs
    monkeypatch.setattr("c4d_pipeline.dust3r_pointmaps.free_memory", lambda d: free)
    assert source._auto_batch(32, 48) == 7


def test_out_of_memory_halves_the_batch(monkeypatch):
    """A fake GPU that runs out of memory above 2 pairs: same pointmaps, in smaller batches."""
    torch.manual_seed(0)
    source = Dust3rPointmaps(Dust3rNet(TINY_NET), device="cpu", batch_size=8)
    frames = np.random.default_rng(1).integers(0, 256, (6, 32, 32, 3), dtype=np.uint8)
    edges = np.array([[i, (i + 1) % 6] for i in range(6)] + [[0, 3], [3, 0]])
    expected = source.pointmaps(frames, edges)
    run, sizes = source._run, []

    def small_gpu(images, idx_i, idx_j):
        sizes.append(len(idx_i))
        if len(idx_i) > 2:
            raise torch.cuda.OutOfMemoryError("fake: out of memory")
        return run(images, idx_i, idx_j)

    monkeypatch.setattr(source, "_run", small_gpu)
    got = source.pointmaps(frames, edges)
    assert sizes == [8, 4, 2, 2, 2, 2]
    np.testing.assert_allclose(got.pts_j, expected.pts_j, rtol=1e-5, atol=1e-6)
    monkeypatch.setattr(source, "_run", lambda *a: (_ for _ in ()).throw(torch.cuda.OutOfMemoryError()))
    with pytest.raises(UserError, match="does not fit in GPU memory"):
        source.pointmaps(frames, edges)


def test_pointmaps_pin_the_frames_for_a_gpu(monkeypatch):
    """The pinning branch (a CUDA device pins the frame tensor before the pair batches copy from
    it), with pinning faked: the pinned tensor is the one the batches read; same pointmaps."""
    torch.manual_seed(0)
    source = Dust3rPointmaps(Dust3rNet(TINY_NET), device="cpu", batch_size=2)
    frames = np.random.default_rng(2).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    edges = np.array([[0, 1], [1, 2], [2, 0]])
    expected = source.pointmaps(frames, edges)
    asked, pinned, read = [], [], []
    monkeypatch.setattr("c4d_pipeline.dust3r_pointmaps.pin_memory", lambda kind: asked.append(kind) or True)
    monkeypatch.setattr(torch.Tensor, "pin_memory", lambda self: pinned.append(self) or self)
    run = source._run
    monkeypatch.setattr(source, "_run", lambda images, i, j: read.append(images) or run(images, i, j))
    got = source.pointmaps(frames, edges)
    assert asked == ["cpu"] and len(pinned) == 1 and pinned[0].shape == (3, 3, 32, 32)
    assert len(read) == 2 and all(images is pinned[0] for images in read)
    for key in ("pts_i", "pts_j", "conf_i", "conf_j"):
        np.testing.assert_array_equal(getattr(got, key), getattr(expected, key))


def test_checkpoint_rng_state_keeps_the_cuda_generators(monkeypatch):
    """rng_state / set_rng_state with CUDA faked: the GPU generators' states go round the trip."""
    gpu_states = [torch.arange(4, dtype=torch.uint8), torch.arange(4, 8, dtype=torch.uint8)]
    restored = []
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_rng_state_all", lambda: gpu_states)
    monkeypatch.setattr(torch.cuda, "set_rng_state_all", restored.append)
    state = train_module.rng_state()
    assert state["cuda"] is gpu_states
    expected = torch.rand(3)
    train_module.set_rng_state(state)
    assert restored == [gpu_states] and torch.equal(torch.rand(3), expected)
