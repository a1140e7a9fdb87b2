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


def _device_check(*args, tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
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
