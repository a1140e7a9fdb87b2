"""benchmarks/device_check.py --cpu: every section runs at tiny sizes and the table is complete."""

import math
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKS = {"shards (c4d datagen)": 1, "DynPT training speed": 2, "DynPT loader": 2,
          "DynPT loader workers per GPU": 1, "DynPT training run": 1,
          "DynPT D-ACC (val)": 1, "DynPT AJ (val)": 1, "DUSt3R pair forward": 2,
          "C4D stage 1 (GA+CMA+CTS)": 2}


def test_device_check_on_the_cpu(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "device_check.py"), "--cpu",
                           "--out", str(tmp_path)], env=env, cwd=ROOT, capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    start = lines.index("| check | setting | result | peak memory |")
    assert lines[start + 1] == "|---|---|---|---|"
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[start + 2:]]
    assert all(len(r) == 4 for r in rows), rows
    assert {name: sum(r[0] == name for r in rows) for name in CHECKS} == CHECKS, rows
    assert not [r for r in rows if r[1] in ("FAILED", "SKIPPED")], rows
    numbers = {r[0] + " / " + r[1]: float(re.match(r"[-\d.]+", r[2]).group()) for r in rows}
    assert all(math.isfinite(v) and v >= 0 for v in numbers.values()), numbers
    speed = [r for r in rows if r[0] == "DynPT training speed"]
    assert [("bf16" in r[1], "fp32" in r[1]) for r in speed] == [(True, False), (False, True)]
    before, after = (float(x) for x in next(r for r in rows if r[0] == "DynPT AJ (val)")[2].split("->"))
    assert 0 <= before <= 100 and 0 <= after <= 100
    assert "--cpu" in lines[start - 2] and "0 section(s) failed" in lines[start - 2]


def _device_check(*args, tmp_path, **environment):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1", **environment}
    return subprocess.run([sys.executable, str(ROOT / "benchmarks" / "device_check.py"), *args,
                           "--out", str(tmp_path)], env=env, cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def test_skip_leaves_sections_out(tmp_path):
    proc = _device_check("--cpu", "--skip", "shards,speed,c4d,loader,run", tmp_path=tmp_path)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    checks = [line.split("|")[1].strip() for line in proc.stdout.splitlines() if line.startswith("| ")][1:]
    assert checks == ["DUSt3R pair forward"] * 2 + ["total"], checks


def test_skip_of_an_unknown_section_is_one_line(tmp_path):
    proc = _device_check("--skip", "dust3r,gpu", tmp_path=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "--skip gpu: no such section; choose from shards,speed,dust3r,c4d,loader,run" in proc.stderr


def _processes_with(variable: str) -> list[int]:
    """The processes whose environment holds `variable` (inherited from a device_check run)."""
    found = []
    for environ in Path("/proc").glob("[0-9]*/environ"):
        try:
            if f"{variable}=".encode() in environ.read_bytes():
                found.append(int(environ.parent.name))
        except OSError:  # gone meanwhile, or not ours to read
            pass
    return found


def test_a_section_past_its_limit_is_killed_and_the_check_goes_on(tmp_path):
    """The shards section (c4d datagen, ~10 s of CPU here) under a 3 s limit: its row says it
    timed out, no process of it is left, and the next section still runs."""
    marker = f"DEVICE_CHECK_RUN_{os.getpid()}"
    proc = _device_check("--cpu", "--skip", "speed,c4d,run", "--section-limit-s", "shards=3",
                         tmp_path=tmp_path, **{marker: "1"})
    assert proc.returncode == 1, proc.stdout[-2000:] + proc.stderr[-3000:]
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in proc.stdout.splitlines()
            if line.startswith("| ")][1:]
    assert rows[0][:3] == ["shards (c4d datagen)", "TIMED OUT",
                           "timed out after 3 s (--section-limit-s); its processes were killed"], rows
    assert [r[0] for r in rows[1:]] == ["DUSt3R pair forward"] * 2 + ["DynPT loader", "total"], rows
    assert rows[3][1:3] == ["SKIPPED", "no shards"], rows
    assert 3 <= int(re.search(r"shards \(c4d datagen\) (\d+) s", rows[4][1])[1]) < 10, rows
    assert "2 section(s) failed" in proc.stdout  # the timed-out section and the one needing it
    assert not _processes_with(marker)
