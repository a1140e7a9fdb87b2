"""CPU threads: the count every command sets from the usable cores and the workers it starts."""

import os
import subprocess
import sys
import time

import cv2
import pytest
import torch

from c4d.cli import run_subcommand
from c4d_core import system
from c4d_core.errors import UserError


@pytest.fixture
def restore_threads(monkeypatch):
    """Undo what a test sets: torch/OpenCV threads, the override, the OMP variables."""
    before = torch.get_num_threads(), cv2.getNumThreads()
    for name in system._THREAD_VARIABLES:
        monkeypatch.setenv(name, os.environ.get(name, "1"))
    monkeypatch.setattr(system, "_USER_OMP", None)
    yield
    system.set_thread_override(None)
    torch.set_num_threads(before[0])
    cv2.setNumThreads(before[1])


def test_cgroup_quota_caps_the_cores(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: set(range(16)))
    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    assert system.available_cpus(tmp_path) == 16  # no cgroup files: the affinity
    (tmp_path / "cpu.max").write_text("150000 100000\n")  # 1.5 CPUs
    assert system.available_cpus(tmp_path) == 2
    (tmp_path / "cpu.max").write_text("max 100000\n")
    assert system.available_cpus(tmp_path) == 16
    (tmp_path / "cpu.max").unlink()
    (tmp_path / "cpu").mkdir()
    (tmp_path / "cpu" / "cpu.cfs_quota_us").write_text("300000\n")  # cgroup v1: 3 CPUs
    (tmp_path / "cpu" / "cpu.cfs_period_us").write_text("100000\n")
    assert system.available_cpus(tmp_path) == 3
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")  # torchrun: two processes share them
    assert system.available_cpus(tmp_path) == 1


def test_workers_take_a_core_each_and_the_main_process_the_rest(restore_threads, monkeypatch):
    monkeypatch.setattr(system, "available_cpus", lambda: 8)
    assert system.configure_threads(workers=3) == 5
    assert torch.get_num_threads() == 5 and os.environ["OMP_NUM_THREADS"] == "5"
    assert system.configure_threads(workers=20) == 1  # never below one
    system.init_worker_threads()
    assert torch.get_num_threads() == 1 and cv2.getNumThreads() == 1


def test_precedence_config_key_then_flag_then_omp_then_automatic(restore_threads, monkeypatch):
    monkeypatch.setattr(system, "available_cpus", lambda: 8)
    monkeypatch.setattr(system, "_USER_OMP", "3")
    assert system.configure_threads() == 3
    system.set_thread_override(2)
    assert system.configure_threads(workers=1) == 2
    assert system.configure_threads(threads=4) == 4
    with pytest.raises(UserError, match="--threads"):
        system.set_thread_override(-1)


def test_every_subcommand_takes_threads(restore_threads, tmp_path, capsys):
    """`--threads` reaches torch before the subcommand runs (here one that fails on its input)."""
    with pytest.raises(UserError):
        run_subcommand(["eval-recon", "--threads", "2", "--pred", str(tmp_path), "--gt", str(tmp_path)])
    assert torch.get_num_threads() == 2


def test_run_threads_is_the_config_key_and_set_before_the_networks_load(restore_threads, tmp_path, capsys):
    """`c4d run --threads N` stands for the key `threads` (both at once: one-line refusal, as for
    the other flags), and the key sets the threads before anything is loaded (it was applied in
    the optimisation only); here the run stops at its missing video, after that point."""
    from c4d.cli import main

    out = tmp_path / "out"
    assert main(["run", str(tmp_path / "none.mp4"), "--threads", "1", "threads=2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "`threads` is set both by a flag and by `threads=...`" in err and len(err.splitlines()) == 1
    torch.set_num_threads(1)
    with pytest.raises(UserError, match="does not exist"):
        run_subcommand(["run", str(tmp_path / "none.mp4"), "threads=3", "--out", str(out)])
    assert torch.get_num_threads() == 3 and cv2.getNumThreads() == 3
    assert not out.exists()


def test_openmp_threads_spin_on_an_idle_machine_and_sleep_on_a_busy_one(monkeypatch):
    """The wait policy follows the cores other processes keep busy at start-up; a user's
    OMP_WAIT_POLICY always wins; an unknown load counts as busy."""
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    assert system.prepare_openmp(busy=0.1) == "default"
    assert "OMP_WAIT_POLICY" not in os.environ
    assert system.prepare_openmp(busy=1.0) == "PASSIVE"  # one CPU-bound process beside us
    assert os.environ["OMP_WAIT_POLICY"] == "PASSIVE"
    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    assert system.prepare_openmp(busy=9.0) == "ACTIVE"
    monkeypatch.delenv("OMP_WAIT_POLICY")
    monkeypatch.setattr(system, "busy_cpus", lambda: None)
    assert system.prepare_openmp() == "PASSIVE"


def test_busy_cpus_sees_a_real_cpu_bound_process(tmp_path):
    """A spinning child process shows as about one busy core; an unreadable counter file as None."""
    cores = len(os.sched_getaffinity(0))
    hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        time.sleep(0.5)
        busy = system.busy_cpus(window_s=0.3)
    finally:
        hog.kill()
        hog.wait()
    assert 0.8 <= busy <= cores
    assert system.busy_cpus(window_s=0.0, stat=tmp_path / "missing") is None


def test_the_wait_policy_is_chosen_before_torch_loads_and_only_then(tmp_path, monkeypatch):
    """A fresh `c4d` process chooses it (and logs it) before the subcommand's module imports
    torch; in a process where torch is loaded (`c4d demo`'s steps, these tests) the choice could
    no longer take effect, so nothing is measured."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    done = subprocess.run([sys.executable, "-m", "c4d", "-v", "eval-recon", "--pred", str(tmp_path),
                           "--gt", str(tmp_path)], capture_output=True, text=True, env=env)
    assert done.returncode == 2 and "OpenMP wait policy: " in done.stderr
    monkeypatch.delenv("OMP_WAIT_POLICY", raising=False)
    monkeypatch.setattr(system, "busy_cpus", lambda: pytest.fail("measured with torch loaded"))
    with pytest.raises(UserError):
        run_subcommand(["eval-recon", "--pred", str(tmp_path), "--gt", str(tmp_path)])


_FAULTS_PER_STEP = """
import resource, sys, torch
from c4d_core.system import prepare_allocator
mode, big = sys.argv[1], int(sys.argv[2])
print(prepare_allocator(every_size=mode == "every") if mode != "off" else "off")
torch.manual_seed(0)
torch.set_num_threads(2)
net = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, padding=1), torch.nn.InstanceNorm2d(8), torch.nn.ReLU(),
                          torch.nn.Conv2d(8, 8, 3, padding=1))
x = torch.randn(16, 3, 64, 64)
def step():
    y = net(x)
    loss = (y[..., 1:] * y[..., :-1]).sum()
    if big:  # and a block of `big` MiB, as a large clip's activations are
        loss = loss + (y.mean() * torch.ones(big << 18)).sum()
    loss.backward()
for _ in range(3):
    step()
faults = []  # per step: the median ignores a one-off burst (a thread's arena growing once)
for _ in range(10):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    step()
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(sorted(faults)[len(faults) // 2])
"""


def _faults_per_step(tmp_path, mode: str, big_mib: int = 0, under_c4d: bool = False,
                     **env) -> tuple[str, float]:
    """(what prepare_allocator returned, median page faults per step) of a real process running
    small training steps; mode: off (glibc's defaults), kept (prepare_allocator()) or every
    (prepare_allocator(every_size=True)); `under_c4d`: its parent called prepare_allocator()."""
    script = tmp_path / "faults.py"
    script.write_text(_FAULTS_PER_STEP)
    base = {k: v for k, v in os.environ.items()
            if not k.startswith(("MALLOC_", "C4D_MALLOC")) and k != "LD_PRELOAD"}
    cmd = [sys.executable, str(script), mode, str(big_mib)]
    if under_c4d:  # started by a process that called prepare_allocator(), as `c4d demo` starts `c4d train`
        cmd = [sys.executable, "-c", "import subprocess, sys; from c4d_core.system import prepare_allocator; "
               f"assert prepare_allocator(); sys.exit(subprocess.run({cmd!r}).returncode)"]
    out = subprocess.run(cmd, env={**base, **env}, check=True, capture_output=True, text=True).stdout.split()
    return out[0], float(out[1])


def test_kept_memory_ends_the_page_faults_of_repeated_training_steps(tmp_path):
    """glibc's defaults hand the steps' memory back to the kernel and fault it in again
    (thousands of faults per step); `prepare_allocator` keeps it; a user's own malloc setting is
    left alone."""
    (off, default), (on, kept) = _faults_per_step(tmp_path, "off"), _faults_per_step(tmp_path, "kept")
    assert (off, on) == ("off", "True")
    assert default > 1000 and kept * 10 < default, (default, kept)
    assert _faults_per_step(tmp_path, "kept", MALLOC_TOP_PAD_="0")[0] == "False"
    assert _faults_per_step(tmp_path, "every", MALLOC_MMAP_MAX_="0")[0] == "False"


def test_training_keeps_blocks_over_the_mmap_threshold_too(tmp_path):
    """Blocks of 48 MiB in each step (over glibc's 32 MiB cap on the mmap threshold; 12,288
    pages each, three a step with the gradient's) are mapped and faulted in afresh at every step
    with the general settings; `c4d train`'s `every_size` takes them from the heap and keeps
    them (measured, median per step: ~37,000 against 0 faults; means ~34,000 against ~600)."""
    _, kept = _faults_per_step(tmp_path, "kept", 48)
    on, every = _faults_per_step(tmp_path, "every", 48)
    assert on == "True"
    assert kept > 24_000 and every * 10 < kept, (kept, every)
    # The settings a c4d parent passed down are not taken for the user's own: applied again.
    on, every = _faults_per_step(tmp_path, "every", 48, under_c4d=True)
    assert on == "True" and every * 10 < kept, every
