"""Installed as users install it: an sdist and a wheel built from it, in a fresh virtual environment.

`make test` itself runs on an editable install; this test builds the distributions with `build`
(the wheel from the sdist, so both must carry the presets), installs the wheel into a new venv
(torch pinned first, as the Makefile does; the other dependencies from the configured package
index or pip's cache) and, from a folder outside the checkout, runs `c4d --help`, `c4d config
show`, a one-scene `c4d datagen` of every preset, `c4d demo --quick` and `c4d view --save` of
its reconstruction (the viewer's assets are package data).
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from c4d_core.config import available_presets

REPO = Path(__file__).resolve().parents[1]
TORCH = os.environ.get("C4D_TEST_TORCH", "torch==2.13.0")  # the Makefile's pin


def _run(argv, cwd, env=None, timeout=900):
    result = subprocess.run([str(a) for a in argv], cwd=cwd, env=env, capture_output=True, text=True,
                            timeout=timeout)
    assert result.returncode == 0, f"{argv}\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result.stdout


def _source_tree(target: Path) -> Path:
    """The checkout's files as a clean clone has them (tracked and not ignored), copied to `target`
    so that building leaves nothing in the checkout."""
    listed = _run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], REPO)
    for name in filter(None, listed.split("\0")):
        if (REPO / name).is_file():
            (target / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / name, target / name)
    return target


@pytest.mark.slow
def test_wheel_in_a_fresh_venv_runs_from_outside_the_checkout(tmp_path):
    venv, elsewhere = tmp_path / "venv", tmp_path / "elsewhere"
    elsewhere.mkdir()
    python, c4d = venv / "bin" / "python", venv / "bin" / "c4d"
    # Nothing of the checkout on the path (PYTHONPATH would also show pip the build's egg-info).
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(PYOPENGL_PLATFORM="egl", OMP_NUM_THREADS="1", PATH=f"{venv / 'bin'}{os.pathsep}{env['PATH']}")
    _run([sys.executable, "-m", "venv", venv], tmp_path, env)
    pip = [python, "-m", "pip", "install", "--quiet"]
    _run([*pip, *TORCH.split()], tmp_path, env)
    _run([*pip, "build"], tmp_path, env)
    source = _source_tree(tmp_path / "source")
    _run([python, "-m", "build", "--outdir", tmp_path / "dist", source], tmp_path, env)
    (wheel,) = (tmp_path / "dist").glob("c4d-*.whl")
    _run([*pip, wheel], tmp_path, env)

    where = _run([python, "-c", "import c4d, c4d_configs; print(c4d.__file__, c4d_configs.__file__)"], elsewhere, env)
    assert str(REPO) not in where and str(source) not in where and str(venv) in where, where
    assert "datagen" in _run([c4d, "--help"], elsewhere, env)
    assert "stage1_iters: 60" in _run([c4d, "config", "show", "c4d/tiny"], elsewhere, env)
    for preset in available_presets("datagen"):
        _run([c4d, "datagen", "--preset", preset, "--num-scenes", 1, "--out", elsewhere / preset,
              "--resolution", 32, "--frames", 3, "--workers", 1, "tracks.num_points=16"], elsewhere, env)
        assert (elsewhere / preset / "train-000000.tar").is_file()
    _run([c4d, "demo", "--quick", "--out", elsewhere / "demo"], elsewhere, env, timeout=1500)
    assert (elsewhere / "demo" / "summary.md").is_file()
    # the viewer page, with the three.js the wheel carries as package data
    _run([c4d, "view", elsewhere / "demo" / "reconstruct" / "scene-000" / "c4d", "--save",
          elsewhere / "view.html"], elsewhere, env)
    page = (elsewhere / "view.html").read_text()
    assert '<script type="importmap">{"imports": {"three": "data:text/javascript;base64,' in page
    assert 'id="c4d-payload"' in page and len(page) > 700_000
