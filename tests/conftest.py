"""Suite-wide settings.

Tiny torch models run fastest single-threaded; on a shared 2-core machine two OpenMP threads can
be 100x slower (spin-waiting), so every test runs with one torch thread (subprocesses too).
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import pytest  # noqa: E402
import torch  # noqa: E402


@pytest.fixture(autouse=True, scope="session")
def one_torch_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
