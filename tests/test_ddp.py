"""DDP in real processes on the CPU: torchrun (gloo) runs of the tiny model, a few steps each.

Every run sets DYNPT_DEBUG_DUMP, so each rank appends, per optimiser step, a SHA-256 of its
weights and the scene keys it read (dynpt.train.Trainer._debug_dump). Three launches:
- "nodes": `--nnodes 2`, one process per node, two torchrun launches with a c10d rendezvous on
  127.0.0.1 (a free port): 6 steps without interruption, the reference;
- "split": 2 processes on one node, 3 steps (`train.stop_after=3`) through
  `c4d train --nproc-per-node 2`, then `--resume` under `torchrun --nproc_per_node 2` for the last
  3. The same world size, seed and data give the same run as "nodes", bit for bit.
"""

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import torch

from c4d_core.system import available_cpus
from tests.dynpt_testdata import synthetic_shards

NUM_SCENES = 16  # one per shard: 8 per rank and epoch, more than the 6 steps x 1 clip read
ROOT = Path(__file__).resolve().parents[1]


def _overrides(shards, out_dir) -> list[str]:
    return [f"data.sources=[{shards}]", f"train.out_dir={out_dir}", "data.crop_size=[32,32]",
            "data.num_frames=6", "data.num_tracks=12", "data.shuffle_buffer=4",
            "train.total_batch=2", "train.batch_size=1", "train.steps=6", "train.ckpt_every=3",
            "train.log_every=1", "eval.every=0"]


TORCHRUN = [sys.executable, "-m", "torch.distributed.run"]


def _start(command: list[str], dump: Path | None = None, threads: str | None = "1") -> subprocess.Popen:
    """`command` in a process of its own; OMP_NUM_THREADS=`threads` (None: unset, the launcher's
    own choice)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}
    env |= {"PYTHONPATH": str(ROOT), **({"OMP_NUM_THREADS": threads} if threads else {})}
    if dump is not None:
        env["DYNPT_DEBUG_DUMP"] = str(dump)
    return subprocess.Popen(command, env=env, cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _torchrun(launcher: list[str], args: list[str], dump: Path) -> subprocess.Popen:
    return _start([*TORCHRUN, *launcher, "-m", "dynpt.cli_train", "--config", "tiny-cpu", *args], dump)


def _wait(*processes: subprocess.Popen, timeout: float = 300, grace: float = 30) -> list[str]:
    """All launches exit 0; once one fails the others get `grace` seconds (a torchrun agent whose
    peer died waits in its exit barrier for minutes), then every launch's output is shown.
    Returns their outputs."""
    outputs: list[list[str]] = [[] for _ in processes]
    readers = [threading.Thread(target=lambda p=p, o=o: o.append(p.stdout.read()), daemon=True)
               for p, o in zip(processes, outputs)]
    for reader in readers:
        reader.start()
    deadline = time.monotonic() + timeout
    while any(p.poll() is None for p in processes) and time.monotonic() < deadline:
        if any(p.returncode not in (None, 0) for p in processes):
            deadline = min(deadline, time.monotonic() + grace)
        time.sleep(0.2)
    for p in processes:
        if p.poll() is None:
            p.kill()
    for reader in readers:
        reader.join()
    report = [f"launch {i}: exit {p.wait()}\n{''.join(o)[-3000:]}"
              for i, (p, o) in enumerate(zip(processes, outputs))]
    assert all(p.returncode == 0 for p in processes), "\n\n".join(report)
    return ["".join(o) for o in outputs]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _dump(folder: Path) -> dict[int, list[dict]]:
    return {int(p.stem.split("_")[1]): [json.loads(l) for l in p.read_text().splitlines()]
            for p in sorted(folder.glob("rank_*.jsonl"))}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ddp")
    shards = synthetic_shards(NUM_SCENES, 1)
    port = _free_port()
    nodes = [_torchrun(["--nnodes", "2", "--nproc_per_node", "1", "--node_rank", str(k),
                        "--rdzv_backend", "c10d", "--rdzv_endpoint", f"127.0.0.1:{port}",
                        "--rdzv_id", "test-ddp"], _overrides(shards, tmp / "nodes"),
                       tmp / "dump-nodes") for k in (0, 1)]
    _wait(*nodes)
    split = _overrides(shards, tmp / "split")  # the first half through `c4d train`'s launcher
    _wait(_start([sys.executable, "-m", "c4d", "train", "--nproc-per-node", "2", "--config",
                  "tiny-cpu", *split, "train.stop_after=3"], tmp / "dump-split"))
    _wait(_torchrun(["--standalone", "--nproc_per_node", "2"], ["--resume", *split],
                    tmp / "dump-split"))
    return tmp


@pytest.mark.parametrize("name", ["nodes", "split"])
def test_ranks_hold_identical_weights_and_read_disjoint_scenes(runs, name):
    dump = _dump(runs / f"dump-{name}")
    assert sorted(dump) == [0, 1]
    for rank in (0, 1):
        assert [r["step"] for r in dump[rank]] == list(range(1, 7)), (name, rank)
    for a, b in zip(dump[0], dump[1]):
        assert a["weights"] == b["weights"], f"{name}: ranks differ after step {a['step']}"
    scenes = [{s for r in dump[rank] for s in r["scenes"]} for rank in (0, 1)]
    assert all(len(r["scenes"]) == 1 for rank in (0, 1) for r in dump[rank])  # 2 clips, 2 ranks
    assert scenes[0] and scenes[1] and not scenes[0] & scenes[1], scenes


def test_resume_under_torchrun_continues_exactly(runs):
    """3 steps + --resume 3 steps on 2 processes == 6 uninterrupted steps on 2 nodes, bit for bit."""
    split, nodes = _dump(runs / "dump-split")[0], _dump(runs / "dump-nodes")[0]
    assert [r["weights"] for r in split] == [r["weights"] for r in nodes]
    assert [r["scenes"] for r in split] == [r["scenes"] for r in nodes]
    a = torch.load(runs / "nodes" / "checkpoints" / "step_00000006.pt", weights_only=True)
    b = torch.load(runs / "split" / "checkpoints" / "step_00000006.pt", weights_only=True)
    for key, value in a["model"].items():
        assert torch.equal(value, b["model"][key]), key


@pytest.mark.parametrize("name", ["nodes", "split"])
def test_only_rank_0_writes_checkpoints_and_logs(runs, name):
    out = runs / name
    log = [json.loads(l) for l in (out / "log.jsonl").read_text().splitlines()]
    assert [r["step"] for r in log] == list(range(1, 7))  # one line per step, not one per rank
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == [
        "last.pt", "step_00000003.pt", "step_00000006.pt"]  # last.pt: the newest, as a link
    events = list((out / "tb").glob("events.out.tfevents.*"))
    assert len(events) == (1 if name == "nodes" else 2)  # one writer per launch (split: 2 launches)
    ckpt = torch.load(out / "checkpoints" / "step_00000006.pt", weights_only=False)
    assert len(ckpt["extra"]["rng"]) == 2 and len(ckpt["extra"]["data"]) == 2  # both ranks' state


def test_the_launcher_divides_the_cores_among_its_processes(tmp_path):
    """`c4d train --nproc-per-node 2` without OMP_NUM_THREADS: each process takes half the usable
    cores, not the launcher's own count of all of them (4 threads on 2 cores: steps 10x slower)."""
    args = ["--config", "tiny-cpu", *_overrides(synthetic_shards(NUM_SCENES, 1), tmp_path / "run"),
            "train.steps=3"]
    out, = _wait(_start([sys.executable, "-m", "c4d", "train", "--nproc-per-node", "2", *args],
                        threads=None))
    assert f"training on 2 process(es) x {max(1, available_cpus() // 2)} thread(s), cpu" in out, out


def test_a_schedule_mistake_is_one_line(tmp_path):
    """total_batch not divisible by batch_size x processes: `c4d train --nproc-per-node` says so
    before starting any process; under torchrun only rank 0 says it (torchrun adds its report)."""
    args = ["--config", "tiny-cpu", f"data.sources=[{synthetic_shards(NUM_SCENES, 1)}]",
            f"train.out_dir={tmp_path / 'run'}"]
    ours = _start([sys.executable, "-m", "c4d", "train", "--nproc-per-node", "2", *args])
    theirs = _start([*TORCHRUN, "--standalone", "--nproc_per_node", "2", "-m", "dynpt.cli_train", *args])
    message = ("c4d: error: train.total_batch=4 is not a multiple of train.batch_size=4 x 2 "
               "processes; choose total_batch as a multiple of 8")
    out, _ = ours.communicate(timeout=120)
    assert ours.returncode == 2 and out.strip() == message
    out, _ = theirs.communicate(timeout=120)
    assert theirs.returncode != 0 and out.count("c4d: error:") == 1 and message in out
    assert not (tmp_path / "run").exists()
