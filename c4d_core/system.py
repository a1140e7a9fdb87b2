"""The system under the project: library checks with messages that say how to fix them, the
CPU threads every command uses (`configure_threads`), how freed memory is kept
(`prepare_allocator`) and how much is still available (`available_memory`)."""

from __future__ import annotations

import ctypes.util
import logging
import math
import os
import sys
import time
from pathlib import Path

from c4d_core.errors import UserError

log = logging.getLogger(__name__)

EGL_HELP = (
    "install Mesa's EGL and GL drivers, e.g. on Debian/Ubuntu: "
    "`sudo apt-get install libegl1 libegl-mesa0 libgl1-mesa-dri libgles2`"
)


def require_egl() -> None:
    """Select PyOpenGL's EGL platform and check that libEGL can be loaded.

    Must run before `pyrender` or `OpenGL` is imported. Raises `UserError` naming the fix.
    """
    platform = os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if platform != "egl":
        raise UserError(
            f"PYOPENGL_PLATFORM is {platform!r}, but offscreen rendering needs 'egl': "
            "unset it or set PYOPENGL_PLATFORM=egl"
        )
    if ctypes.util.find_library("EGL") is None:
        raise UserError(f"libEGL was not found, so nothing can be rendered: {EGL_HELP}")
    problem = pyopengl_problem(sys.version_info[:2], _installed_version("PyOpenGL"))
    if problem:
        raise UserError(problem)


def _installed_version(distribution: str) -> str | None:
    from importlib import metadata

    try:
        return metadata.version(distribution)
    except metadata.PackageNotFoundError:
        return None


def pyopengl_problem(python: tuple[int, int], version: str | None) -> str | None:
    """Why PyOpenGL `version` cannot render on Python `python` (major, minor), or None.

    PyOpenGL before 3.1.7 (pyrender pins 3.1.0) fails at the first GL call on Python 3.12 and
    newer ("No array-type handler for type _ctypes.type"); pyrender runs with 3.1.7 and later.
    """
    if version is None or python < (3, 12):
        return None
    release = tuple(int(part) for part in version.split(".")[:3] if part.isdigit())
    if release >= (3, 1, 7):
        return None
    return (f"PyOpenGL {version} cannot render on Python {python[0]}.{python[1]} (it fails at the first "
            "GL call); install 3.1.7 or later: `pip install 'PyOpenGL>=3.1.7'` (pip warns that "
            "pyrender pins 3.1.0; pyrender works with the newer one)")


# --- memory allocator ----------------------------------------------------------------------------

# glibc malloc settings: (environment variable, mallopt parameter, value). Blocks up to 32 MiB
# (glibc's largest automatic mmap threshold) come from the heap instead of fresh mappings, and
# freed memory is kept for reuse (64 MiB at the top of each thread's heap, up to 1 GiB at the top
# of the main heap) instead of handed back to the kernel and faulted in again, page by page.
_MALLOC_SETTINGS = (
    ("MALLOC_MMAP_THRESHOLD_", -3, 32 << 20),  # M_MMAP_THRESHOLD
    ("MALLOC_TOP_PAD_", -2, 64 << 20),  # M_TOP_PAD
    ("MALLOC_TRIM_THRESHOLD_", -1, 1 << 30),  # M_TRIM_THRESHOLD
)
# With `every_size`, for a loop that allocates the same tensors at every step (training): blocks
# of every size come from the heap (no mapping: glibc caps the mmap threshold at 32 MiB, and a
# training step's activations are larger) and the heap is never trimmed, so the memory of one
# step's peak is reused by the next, as PyTorch's caching allocator keeps it on a GPU.
_MALLOC_EVERY_SIZE = (
    ("MALLOC_MMAP_MAX_", -4, 0),  # M_MMAP_MAX: no block mapped on its own
    ("MALLOC_TRIM_THRESHOLD_", -1, -1),  # M_TRIM_THRESHOLD; -1: never trim (mallopt(3))
)
# Set beside the variables: a child process (`c4d demo`'s `c4d train`, torchrun's workers) that
# finds them tells its parent's settings from the user's by it.
_MARKER, _MARKER_VALUE = "C4D_MALLOC", "prepare_allocator"
# The user chose an allocator or malloc settings before this process started.
_USER_MALLOC = (bool(os.environ.get("LD_PRELOAD")) or "malloc" in os.environ.get("GLIBC_TUNABLES", "")
                or (os.environ.get(_MARKER) != _MARKER_VALUE
                    and any(name in os.environ for name, _, _ in (*_MALLOC_SETTINGS, *_MALLOC_EVERY_SIZE))))


def prepare_allocator(every_size: bool = False) -> bool:
    """Keep freed memory in this process and its children for reuse; return whether it was set.

    With glibc's defaults a training step returns its temporaries' memory to the kernel and takes
    it back as fresh zeroed pages on the next step: ~20,000 page faults per step of the demo's
    training (tiny-cpu-2x, batch 4), under 500 with these settings, and the step 0.87x the time
    (docs/perf/threads.md). Peak memory is unchanged; the process keeps it until it exits, as
    PyTorch's caching allocators do. `every_size` (`c4d train`) keeps blocks over 32 MiB too: at
    the paper's clip scaled to this CPU (24x192x256, 192 tracks) a step with glibc's defaults
    faulted in ~19 GiB of pages; with every block kept it took 0.83x the CPU time (36.7 against
    44.0 CPU-s) and 0.95x the peak (docs/PERFORMANCE.md). Applied now (mallopt) and, for child
    processes, through glibc's environment variables (marked as ours, so that a child's own call
    applies them again). Left alone where the user chose an allocator or malloc settings
    (LD_PRELOAD, GLIBC_TUNABLES, a MALLOC_*_ variable) and off glibc."""
    if _USER_MALLOC:
        return False
    try:
        libc = ctypes.CDLL(None)
        libc.gnu_get_libc_version  # only glibc has it (and these parameters)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    for _, param, value in _malloc_settings(every_size):
        if not mallopt(param, value):
            return False
    os.environ.update(allocator_environment(every_size))
    return True


def allocator_environment(every_size: bool = False) -> dict[str, str]:
    """`prepare_allocator`'s settings as glibc's environment variables: a process started with
    them (one that does not call it, such as another project's script) gets the same allocator."""
    return {name: str(value) for name, _, value in _malloc_settings(every_size)} | {_MARKER: _MARKER_VALUE}


def _malloc_settings(every_size: bool) -> tuple[tuple[str, int, int], ...]:
    return (*_MALLOC_SETTINGS, *(_MALLOC_EVERY_SIZE if every_size else ()))


# --- CPU threads ---------------------------------------------------------------------------------

# Libraries that size their own thread pools from these variables when they first load.
_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "LP_NUM_THREADS")
_override: dict[str, int] = {}
# OMP_NUM_THREADS as the user set it before this process changed it (None: not set).
_USER_OMP = os.environ.get("OMP_NUM_THREADS")
AUTOMATIC = "threads from the usable cores (--threads N chooses them)"  # without OMP_NUM_THREADS


# Below this many busy cores (of those this process may use) no other CPU-bound process runs
# beside this one: one busy process keeps a core at 1.0.
IDLE_BUSY_CPUS = 0.5


def prepare_openmp(busy: float | None = None) -> str:
    """Choose how idle OpenMP threads wait, unless the user set `OMP_WAIT_POLICY`; return the policy.

    Must run before torch is imported (OpenMP reads it once). busy: cores kept busy by other
    processes, summed over the cores this process may use (None: measured, `busy_cpus`). On an
    idle machine (busy < IDLE_BUSY_CPUS) threads keep OpenMP's default of spinning briefly between
    parallel regions ("default"): sleeping there made the demo's small training step 1.35-1.65x
    slower. On a machine busy with other CPU-bound processes they sleep ("PASSIVE"): a spinning
    thread that waits for a peer the OS has descheduled burns the core that peer needs, which made
    training steps 4-10x slower (docs/perf/threads.md). An OMP_NUM_THREADS that is not a
    positive integer is dropped with a warning (`positive_variable`) before OpenMP reads it.
    """
    if positive_variable("OMP_NUM_THREADS", os.environ.get("OMP_NUM_THREADS"), AUTOMATIC) is None:
        os.environ.pop("OMP_NUM_THREADS", None)  # else OpenMP complains in two lines as it loads
    if "OMP_WAIT_POLICY" in os.environ:
        return os.environ["OMP_WAIT_POLICY"]
    if busy is None:
        busy = busy_cpus()
    if busy is not None and busy < IDLE_BUSY_CPUS:
        return "default"
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"  # busy, or unknown: the safe choice
    return "PASSIVE"


def busy_cpus(window_s: float = 0.1, stat: Path = Path("/proc/stat")) -> float | None:
    """Cores busy while this process sleeps for window_s, summed over its affinity mask (0.0: all
    idle, 1.0: one core's worth), from the kernel's per-core counters; None where unreadable.

    A snapshot rather than the load average, which still counts a job that ended a minute ago."""
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None

    def counters() -> dict[int, tuple[int, int]]:  # core -> (all ticks, idle + iowait ticks)
        out = {}
        for line in stat.read_text().splitlines():
            name, *fields = line.split()
            if name.startswith("cpu") and name[3:].isdigit() and (cores is None or int(name[3:]) in cores):
                ticks = [int(f) for f in fields[:8]]  # user nice system idle iowait irq softirq steal
                out[int(name[3:])] = (sum(ticks), ticks[3] + ticks[4])
        return out

    try:
        before = counters()
        time.sleep(window_s)
        after = counters()
    except (OSError, ValueError, IndexError):
        return None
    busy = 0.0
    for core, (total, idle) in after.items():
        if core in before and total > before[core][0]:
            busy += 1.0 - (idle - before[core][1]) / (total - before[core][0])
    return busy if after else None


def _cgroup_cpu_limit(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """CPUs granted by the cgroup quota (v2 `cpu.max`, v1 `cpu.cfs_quota_us`), None if unlimited."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 else quota / period
    except (OSError, ValueError):
        return None


def available_cpus(cgroup_root: Path = Path("/sys/fs/cgroup")) -> int:
    """CPU cores this process may use: its affinity mask, capped by a cgroup CPU quota (rounded
    up), divided among the local ranks of a `torchrun` job (`LOCAL_WORLD_SIZE`). At least 1."""
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    quota = _cgroup_cpu_limit(cgroup_root)
    if quota is not None:
        cpus = min(cpus, math.ceil(quota))
    ranks = positive_variable("LOCAL_WORLD_SIZE", os.environ.get("LOCAL_WORLD_SIZE"),
                              "1 process on this machine") or 1
    return max(1, cpus // ranks)


def available_memory(meminfo: Path = Path("/proc/meminfo"),
                     cgroup_root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """Bytes this process can still allocate without swapping: the kernel's MemAvailable, capped
    by what a cgroup memory limit leaves (v2 `memory.max` less `memory.current`, v1
    `memory.limit_in_bytes` less `memory.usage_in_bytes`); None where none of them can be read."""
    found = []
    try:
        fields = dict(line.split(":", 1) for line in meminfo.read_text().splitlines() if ":" in line)
        found.append(int(fields["MemAvailable"].split()[0]) * 1024)  # kB
    except (OSError, ValueError, KeyError, IndexError):
        pass
    for limit, usage in (("memory.max", "memory.current"),
                         ("memory/memory.limit_in_bytes", "memory/memory.usage_in_bytes")):
        try:
            found.append(int((cgroup_root / limit).read_text()) - int((cgroup_root / usage).read_text()))
        except (OSError, ValueError):  # missing, or "max": no limit
            pass
    return max(0, min(found)) if found else None


def gib(size: float) -> str:
    """A byte count in GiB for a message: '9313.2 GiB'."""
    return f"{size / 2**30:.1f} GiB"


def set_thread_override(threads: int | None) -> None:
    """Remember a user's `--threads`/`threads=` choice (None or 0: automatic) for this process."""
    if threads is not None and threads < 0:
        raise UserError(f"--threads must be 0 (automatic) or a positive count, got {threads}")
    _override.clear()
    if threads:
        _override["threads"] = int(threads)


def configure_threads(workers: int = 0, threads: int | None = None) -> int:
    """Set this process's intra-op thread count (torch, OpenCV) and return it.

    workers: single-threaded worker processes this command starts beside this one (data loader or
    scene generation workers); they get a core each and this process the rest, at least one.
    threads: an explicit count (a config's `threads` key; 0 or None: automatic); otherwise the
    count given to `set_thread_override` (the `--threads` flag), otherwise the user's
    OMP_NUM_THREADS, otherwise automatic.
    Libraries that start later (and child processes) inherit the count through OMP_NUM_THREADS etc.
    """
    count = _thread_count(workers, threads)
    _set_threads(count)
    return count


def export_threads_for(processes: int, workers: int = 0, threads: int | None = None) -> int:
    """Before this process starts `processes` peers on this machine (`c4d train --nproc-per-node`,
    whose processes each call `configure_threads`): set the thread variables they inherit so that
    together they use the usable cores once, and return each one's count. As `configure_threads`
    chooses: `threads`, the `--threads` count or the user's OMP_NUM_THREADS where given, else this
    process's usable cores divided among them, less `workers` each (at least 1). Without it each
    would take the count this process exported for itself (every core) for the user's choice: with
    2 processes on 2 cores, 4 spinning threads made the demo's training steps 10x slower."""
    count = _thread_count(workers, threads, processes)
    _export_threads(count)
    return count


def _thread_count(workers: int, threads: int | None, processes: int = 1) -> int:
    """`threads`, else the `--threads` count, else the user's OMP_NUM_THREADS, else the usable
    cores shared by `processes` processes, less `workers` each (at least 1)."""
    return (threads or _override.get("threads") or _user_omp_threads()
            or max(1, available_cpus() // processes - workers))


def _user_omp_threads() -> int | None:
    return positive_variable("OMP_NUM_THREADS", _USER_OMP, AUTOMATIC)


_warned: set[tuple[str, str]] = set()  # (variable, value) pairs already warned about


def positive_variable(name: str, text: str | None, instead: str) -> int | None:
    """Environment variable `name`'s value `text` as a positive integer; None where it is unset
    or empty, and where it is not one, with a one-line warning (once per value) that it is
    ignored and `instead` is used."""
    if not text:
        return None
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value > 0:
        return value
    if (name, text) not in _warned:
        _warned.add((name, text))
        log.warning("%s=%r is not a positive integer; ignored, using %s", name, text, instead)
    return None


def init_worker_threads(*_args) -> None:
    """Initializer of a worker process (DataLoader `worker_init_fn`, process pools): one thread."""
    _set_threads(1)


def _export_threads(count: int) -> None:
    """The thread variables that libraries loaded later and child processes read."""
    for name in _THREAD_VARIABLES:
        os.environ[name] = str(count)


def _set_threads(count: int) -> None:
    _export_threads(count)
    # Libraries already loaded are set directly (this floor module does not import them).
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(count)
    if "cv2" in sys.modules:
        sys.modules["cv2"].setNumThreads(count)
