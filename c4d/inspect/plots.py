"""Matplotlib figures of the reports (Agg backend: no display needed), saved as PNG."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (after choosing the backend)
import numpy as np  # noqa: E402

from c4d_core import draw  # noqa: E402
from c4d_core.files import atomic_path  # noqa: E402
from datagen.scene import Scene  # noqa: E402

DPI = 100


def _save(fig, path: str | os.PathLike) -> Path:
    """Save through a temporary name, close the figure, return the path."""
    path = Path(path)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=DPI)
    finally:
        plt.close(fig)
    return path


def histogram_grid(path: str | os.PathLike, series: dict[str, tuple[np.ndarray, str]],
                   columns: int = 4) -> Path:
    """One histogram per entry `title -> (values 1-D, x-axis unit)`, in a grid; empty ones say so."""
    rows = int(np.ceil(len(series) / columns))
    fig, axes = plt.subplots(rows, columns, figsize=(4 * columns, 3 * rows), squeeze=False)
    for ax, (title, (values, unit)) in zip(axes.flat, series.items()):
        values = np.asarray(values, np.float64)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel(unit, fontsize=9)
        if values.size == 0:
            ax.text(0.5, 0.5, "not recorded", ha="center", va="center", transform=ax.transAxes)
            continue
        if np.ptp(values) == 0:  # one value: a histogram of it would be a single wide bar
            shown = f"{values[0]:.4g}" + ("" if unit == "count" else f" {unit}")
            ax.text(0.5, 0.5, f"all {values.size} values\n= {shown}", ha="center",
                    va="center", transform=ax.transAxes, fontsize=11)
            ax.set_xticks([])
            ax.set_yticks([])
            continue
        whole = np.allclose(values, np.round(values)) and np.ptp(values) < 60
        integer = unit in ("count", "frames") and whole  # one bar per value
        bins = np.arange(values.min() - 0.5, values.max() + 1.5) if integer else 20
        ax.hist(values, bins=bins, color="#4477aa", edgecolor="white")
        ax.axvline(values.mean(), color="#cc3311", linewidth=1)  # the mean, named in the title
        ax.set_title(f"{title} (red: mean {values.mean():.3g})", fontsize=10)
        ax.set_ylabel("count", fontsize=9)
        ax.ticklabel_format(axis="x", useOffset=False)
    for ax in list(axes.flat)[len(series):]:
        ax.axis("off")
    fig.tight_layout()
    return _save(fig, path)


def track_curves(path: str | os.PathLike, scene: Scene, max_tracks: int) -> Path:
    """A scene's tracks over time: per-frame displacement coloured by mobility, visibility, moving
    fraction per frame. At most `max_tracks` evenly chosen tracks are drawn."""
    t = np.arange(scene.num_frames)
    chosen = np.unique(np.linspace(0, scene.num_tracks - 1, min(max_tracks, scene.num_tracks)).astype(int))
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.5))
    static_c, moving_c = (np.array(c) / 255 for c in (draw.STATIC_COLOR, draw.MOVING_COLOR))

    if scene.displacement is not None:
        for n in chosen:
            moving = scene.moving[n].any() if scene.moving is not None else False
            axes[0].plot(t, scene.displacement[n], color=moving_c if moving else static_c, alpha=0.5, lw=1)
        threshold = scene.meta.get("mobility_threshold")
        if threshold is not None:
            axes[0].axhline(threshold, color="k", ls="--", lw=1, label=f"threshold {threshold}")
            axes[0].legend(fontsize=8)
        axes[0].set_yscale("symlog", linthresh=1e-3)
        axes[0].set_ylim(bottom=0)  # a displacement is a distance: no negative ticks
    axes[0].set_title("world displacement per frame (red: moves at some frame)", fontsize=10)
    axes[0].set_xlabel("frame")

    visible = ~scene.occluded[chosen]  # (n,T)
    axes[1].imshow(visible, aspect="auto", cmap="gray", interpolation="nearest", vmin=0, vmax=1)
    axes[1].set_title("visibility (white = visible) of drawn tracks", fontsize=10)
    axes[1].set_xlabel("frame")
    axes[1].set_ylabel("track")

    if scene.moving is not None and scene.num_tracks:
        axes[2].plot(t, scene.moving.mean(axis=0), color=moving_c, label="all tracks")
        vis_all = ~scene.occluded
        per_frame = (scene.moving & vis_all).sum(0) / np.maximum(vis_all.sum(0), 1)
        axes[2].plot(t, per_frame, color="k", ls="--", label="visible tracks")
        axes[2].set_ylim(0, 1)
        axes[2].legend(fontsize=8)
    axes[2].set_title("moving fraction per frame", fontsize=10)
    axes[2].set_xlabel("frame")
    fig.tight_layout()
    return _save(fig, path)


def trajectory_plot(path: str | os.PathLike, positions: np.ndarray, label: str,
                    reference: np.ndarray | None = None, title: str = "camera trajectory",
                    unit: str = "world units", others: dict[str, np.ndarray] | None = None) -> Path:
    """Camera centres (T,3) of the method named `label` (e.g. "C4D") as a top view (x, y) and a
    side view (x, z), optionally with a ground-truth trajectory (T,3) and `others` (label -> (T,3),
    e.g. GA only) already aligned to the same frame; axes in `unit`."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5))
    for ax, (i, j, name) in zip(axes, ((0, 1, "top view (x, y)"), (0, 2, "side view (x, z)"))):
        if reference is not None:
            ax.plot(reference[:, i], reference[:, j], "-", color="#999999", lw=5, alpha=0.6,
                    label="ground truth")  # wide, so it shows under a perfect estimate
        for (other_label, other), color in zip((others or {}).items(), ("#0077bb", "#009988", "#ee7733")):
            ax.plot(other[:, i], other[:, j], "--", color=color, lw=1.2, label=other_label)
        ax.plot(positions[:, i], positions[:, j], "-o", color="#cc3311", ms=2, label=label)
        ax.plot(positions[:1, i], positions[:1, j], "s", color="#cc3311", ms=6, label="first frame")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(f"{'xyz'[i]} ({unit})", fontsize=9)
        ax.set_ylabel(f"{'xyz'[j]} ({unit})", fontsize=9)
        ax.set_aspect("equal", adjustable="datalim")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), fontsize=9, frameon=False)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout(rect=(0, 0.07, 1, 1))  # the legend below the axes, never over a line
    return _save(fig, path)
