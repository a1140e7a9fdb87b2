"""The figures README.md and docs/RESULTS.md section 1 give for `make demo` are those of the run
they describe, and that run shows what they say of it.

docs/results/demo/ holds the run's own records, copied from its output folder: summary.md, the
eval and paper-eval steps' eval.json (as eval.json and paper-eval.json) and the reconstruct
step's metrics.json (as reconstruct.json). Each claim below is a pattern of a page whose numbers
must equal the records' as the page rounds them, and where a page says the tracker or C4D beats
a baseline, the records must show it. A figure edited by hand, or a new run whose records are
copied without the pages following (or the reverse), fails here. What the README says each
command line gives at toy sizes is checked by running it (tests/test_readme_commands.py).
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from c4d.demo import interval_key
from dynpt.evaluate import signed

ROOT = Path(__file__).resolve().parents[1]
RECORDS = ROOT / "docs" / "results" / "demo"
PRESETS = ("movi-e", "movi-e-panning")
STEPS = ("data", "train", "eval", "paper-eval", "recon-data", "reconstruct", "pictures")


def records() -> dict:
    return {name: json.loads((RECORDS / f"{name}.json").read_text())
            for name in ("eval", "paper-eval", "reconstruct")}


def step_seconds() -> dict[str, float]:
    """step -> seconds, from the step table of the run's summary.md."""
    rows = re.findall(r"^\| ([a-z-]+) \| ([0-9.]+) \|$", (RECORDS / "summary.md").read_text(), re.M)
    return {step: float(seconds) for step, seconds in rows}


def section(path: str, heading: str | None = None) -> str:
    """The text of `path`, or of its section from the line starting with `heading` to the next
    heading of the same level."""
    text = (ROOT / path).read_text()
    if heading is None:
        return text
    start = text.index("\n" + heading) + 1
    level = heading.split(" ")[0] + " "
    end = text.find("\n" + level, start + len(heading))
    return text[start:end if end > 0 else None]


def one(text: str, pattern: str) -> tuple[str, ...]:
    """The groups of the one match of `pattern` in `text` (whitespace in the pattern matches any
    run of white space, as the pages wrap lines)."""
    pattern = re.sub(r"\\? ", r"\\s+", pattern)
    found = re.findall(pattern, text)
    assert len(found) == 1, f"{len(found)} matches of {pattern!r}"
    return found[0] if isinstance(found[0], tuple) else (found[0],)


def paper(rec: dict, preset: str, tracker: str = "dynpt") -> tuple[dict, dict, list[float]]:
    """The paper-protocol summaries of `tracker` ("dynpt": the network's, "dynpt_refined": its
    tracks refined by Lucas-Kanade and its head fused with their epipolar geometry) and
    all-static, and their D-ACC difference's interval."""
    result = rec["paper-eval"][preset]
    return result[tracker], result["zero_motion"], result[interval_key(tracker)]


def scenes(rec: dict) -> list[dict]:
    return [rec["reconstruct"][name] for name in sorted(rec["reconstruct"]) if name.startswith("scene-")]


def test_the_records_are_one_run():
    """The summary's tables hold the JSON records' numbers (they were written by one run)."""
    rec, summary = records(), (RECORDS / "summary.md").read_text()
    for preset in PRESETS:
        dynpt, zero, _ = paper(rec, preset)
        row = f"| {preset} | DynPT (trained here) | {100 * dynpt['d_acc']:.1f} | "
        assert row in summary, row
        row = f"| {preset} | zero motion, all static | {100 * zero['d_acc']:.1f} | "
        assert row in summary, row
    for name, scene in zip(sorted(n for n in rec["reconstruct"] if n.startswith("scene-")), scenes(rec)):
        row = f"| {name} | C4D | {scene['C4D']['pose']['ate']:.4f} |"
        assert row in summary, row
    assert set(step_seconds()) == set(STEPS)


def test_readme_quotes_the_run():
    rec, text = records(), section("README.md")
    seconds = step_seconds()
    times = one(text, r"\(data (\d+) s, train (\d+) s, eval (\d+) s, paper-eval (\d+) s, "
                      r"recon-data (\d+) s, reconstruct (\d+) s, pictures (\d+) s\)")
    assert times == tuple(f"{seconds[s]:.0f}" for s in STEPS)

    aj = [rec["eval"][p][k]["average_jaccard"] for k in ("dynpt", "zero_motion") for p in PRESETS]
    assert one(text, r"AJ (\d+) / (\d+) against (\d+) / (\d+) for zero motion") == \
        tuple(f"{100 * v:.0f}" for v in aj)
    ap = [paper(rec, p)[k]["moving_ap"] for k in (0, 1) for p in PRESETS]
    assert one(text, r"average precision ([0-9.]+) / ([0-9.]+) against ([0-9.]+) / ([0-9.]+) under") == \
        tuple(f"{v:.2f}" for v in ap)
    for preset, pattern, beats in (("movi-e", r"protocol on movi-e, barely \(([+-][0-9.]+), 95 % "
                                              r"interval ([+-][0-9.]+) to ([+-][0-9.]+) points", True),
                                   ("movi-e-panning", r"level with it on panning \(([+-][0-9.]+), "
                                                      r"([+-][0-9.]+) to ([+-][0-9.]+);", False)):
        dynpt, zero, interval = paper(rec, preset)
        assert (interval[0] > 0) == beats, f"the README says DynPT {'beats' if beats else 'is level with'} all-static on {preset}"
        expected = [100 * (dynpt["d_acc"] - zero["d_acc"]), *(100 * v for v in interval)]
        assert one(text, pattern) == tuple(signed(v) for v in expected)
    assert one(text, r"balanced D-ACC (\d+) / (\d+), the target is 75") == \
        tuple(f"{100 * paper(rec, p)[0]['d_acc_balanced']:.0f}" for p in PRESETS)
    assert one(text, r"AJ (\d+) / (\d+) against the network's (\d+) / (\d+) at 256x256") == tuple(
        f"{100 * paper(rec, p, k)[0]['average_jaccard']:.0f}" for k in ("dynpt_refined", "dynpt")
        for p in PRESETS)
    for preset, pattern in (("movi-e", r"on movi-e balanced\s+D-ACC ([0-9.]+) with "
                                       r"D-ACC ([+-][0-9.]+) \(([+-][0-9.]+) to ([+-][0-9.]+)\)"),
                            ("movi-e-panning", r"on panning it reaches ([0-9.]+) and ([+-][0-9.]+)\s+"
                                               r"\(([+-][0-9.]+) to ([+-][0-9.]+)\), the interval above 0")):
        fused, zero, interval = paper(rec, preset, "dynpt_refined")
        expected = [100 * (fused["d_acc"] - zero["d_acc"]), *(100 * v for v in interval)]
        assert one(text, pattern) == (f"{100 * fused['d_acc_balanced']:.1f}",
                                      *(signed(v) for v in expected))
        reached = fused["d_acc_balanced"] >= 0.75 and interval[0] > 0
        assert reached, f"the README says {preset} reaches the target"

    runs = scenes(rec)
    iou = [s["C4D"]["mask"]["iou"] for s in runs]
    every = [s["C4D"]["mask"]["gt_dynamic_fraction"] for s in runs]  # the IoU of an all-dynamic mask
    assert one(text, r"masks of the reconstructions at 256x256 find the tossed objects \(IoU ([0-9.]+) "
                     r"against ([0-9.]+) for every pixel\)") == (f"{np.mean(iou):.2f}", f"{np.mean(every):.2f}")
    assert one(text, r"its motion masks score IoU ([0-9.]+)-([0-9.]+) against ([0-9.]+)-([0-9.]+) for "
                     r"marking every pixel dynamic") == \
        tuple(f"{v:.2f}" for v in (min(iou), max(iou), min(every), max(every)))
    ate = {m: [s[m]["pose"]["ate"] for s in runs] for m in ("C4D", "GA only")}
    better = sum(c < g for c, g in zip(ate["C4D"], ate["GA only"]))
    assert one(text, r"beat GA only's on (\d) of the (\d) scenes \(ATE ([0-9.]+) against ([0-9.]+)\)") == \
        (str(better), str(len(runs)), f"{np.mean(ate['C4D']):.3f}", f"{np.mean(ate['GA only']):.3f}")


def table(text: str, first_header: str) -> list[list[str]]:
    """The body rows of the markdown table whose header starts with `first_header`, cells
    stripped of bold."""
    lines = text[text.index(first_header):].splitlines()
    rows = []
    for line in lines[2:]:
        if not line.startswith("|"):
            break
        rows.append([cell.strip().strip("*") for cell in line.strip("|").split("|")])
    return rows


def test_results_section_1_tables_are_the_run():
    rec, text = records(), section("docs/RESULTS.md", "## 1.")
    names = {"DynPT (trained in the demo)": "dynpt", "zero motion, all static": "zero_motion",
             "all static, zero motion": "zero_motion",
             "the same, head + epipolar mobility": "dynpt_epipolar",
             "the same, LK-refined tracks, head + epipolar mobility": "dynpt_refined"}
    keys = ["d_acc", "d_acc_moving", "d_acc_static", "d_acc_balanced", "average_jaccard",
            "average_pts_within_thresh", "occlusion_accuracy"]
    rows = table(text, "| val set | tracker | D-ACC | moving |")
    assert len(rows) == 6
    for preset, tracker, *cells in rows:
        result = rec["eval"][preset][names[tracker]]
        assert cells == [f"{100 * result[k]:.1f}" for k in keys], (preset, tracker)

    rows = table(text, "| val set | tracker | D-ACC | difference (95 % interval) |")
    assert len(rows) == 6
    for preset, tracker, d_acc, difference, moving, static, balanced, ap, aj in rows:
        kind = names[tracker]
        result, zero, interval = paper(rec, preset, "dynpt" if kind == "zero_motion" else kind)
        result = zero if kind == "zero_motion" else result
        assert [d_acc, moving, static, balanced, ap, aj] == [
            f"{100 * result['d_acc']:.1f}", f"{100 * result['d_acc_moving']:.1f}",
            f"{100 * result['d_acc_static']:.1f}", f"{100 * result['d_acc_balanced']:.1f}",
            f"{result['moving_ap']:.3f}", f"{100 * result['average_jaccard']:.1f}"], (preset, tracker)
        if kind != "zero_motion":
            diff, low, high = (100 * (result["d_acc"] - zero["d_acc"]), *(100 * v for v in interval))
            assert difference == f"{signed(diff)} ({signed(low)} to {signed(high)})"

    rows = table(text, "| scene | C4D ATE | GA only ATE |")
    runs = scenes(rec)
    assert len(rows) == len(runs) + 1
    columns = [[s["C4D"]["pose"]["ate"] for s in runs], [s["GA only"]["pose"]["ate"] for s in runs],
               [s["C4D"]["mask"]["iou"] for s in runs],
               [s["C4D"]["mask"]["gt_dynamic_fraction"] for s in runs]]
    digits = (3, 3, 2, 2)
    for i, (scene, *cells) in enumerate(rows[:-1]):
        assert scene == str(i) and cells == [f"{c[i]:.{d}f}" for c, d in zip(columns, digits)], scene
    assert rows[-1][1:] == [f"{np.mean(c):.{d}f}" for c, d in zip(columns, digits)]


@pytest.mark.parametrize("path", ["README.md", "docs/RESULTS.md"])
def test_the_pages_name_the_run_time_of_the_records(path):
    """Both pages give the run's wall time as the sum of its steps, in minutes."""
    total = sum(step_seconds().values()) / 60
    assert re.search(rf"\b{total:.0f} min\b", section(path)), f"{total:.0f} min"
