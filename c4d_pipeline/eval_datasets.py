"""Readers for the public benchmarks of the paper, for users who have them on disk.

Each loader takes the dataset's root folder in its public layout and returns `EvalSequence`s with
the frames, ground-truth depth and camera-to-world poses of the MonST3R/C4D evaluation protocol:

| dataset      | expected layout under ROOT                                   | protocol                   |
|--------------|--------------------------------------------------------------|----------------------------|
| Sintel       | training/final/SEQ/frame_%04d.png, training/depth/SEQ/*.dpt, | all frames; depth < 70     |
|              | training/camdata_left/SEQ/*.cam                              | (poses: 14 sequences)      |
| TUM-dynamics | SEQ/rgb.txt, SEQ/groundtruth.txt, SEQ/rgb/ (raw download),   | rgb<->pose association     |
|              | or SEQ/rgb_90/ + SEQ/groundtruth_90.txt (prepared)           | (0.02 s), stride 3, first 90 |
| ScanNet      | SCENE/color/N.jpg, SCENE/depth/N.png, SCENE/pose/N.txt       | frames 0, 3, ..., 267      |
| Bonn         | rgbd_bonn_SEQ/rgb/, depth/, groundtruth.txt                  | frames 30..139; depth < 70 |
| KITTI        | depth_selection/val_selection_cropped/{image_gathered,        | first 110 frames; depth>0  |
|              | groundtruth_depth_gathered}/DRIVE_02/*.png                   |                            |

Depth units: Sintel .dpt metres-like units, TUM/Bonn PNG / 5000, ScanNet PNG / 1000, KITTI
PNG / 256 (0 = no measurement). Poses are OpenCV camera-to-world 4x4 (TUM/Bonn files store
`t tx ty tz qx qy qz qw`; Sintel .cam stores a world-to-camera 3x4, inverted here and its camera
centres mean-centred). A layout that does not match raises `UserError` naming what was expected.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from c4d_core.errors import UserError
from c4d_core.geometry import invert_pose
from c4d_pipeline.outputs import read_tum
from c4d_core.video import IMAGE_SUFFIXES

SINTEL_TAG = 202021.25
SINTEL_POSE_SEQUENCES = ("alley_2", "ambush_4", "ambush_5", "ambush_6", "cave_2", "cave_4", "market_2",
                         "market_5", "market_6", "shaman_3", "sleeping_1", "sleeping_2", "temple_2", "temple_3")
TUM_DYNAMIC_SEQUENCES = tuple(f"rgbd_dataset_freiburg3_{m}_{k}" for m in ("sitting", "walking")
                              for k in ("static", "xyz", "halfsphere", "rpy"))
BONN_SEQUENCES = ("balloon2", "crowd2", "crowd3", "person_tracking2", "synchronous")
TUM_FR3_INTRINSICS = np.array([[535.4, 0, 320.1], [0, 539.2, 247.6], [0, 0, 1]], np.float32)


@dataclass
class EvalSequence:
    """One benchmark sequence: image files, optional depth files and poses (T,4,4) cam-to-world."""

    dataset: str
    name: str
    image_paths: list[Path]
    depth_paths: list[Path] | None
    cam_to_world: np.ndarray | None
    read_depth: Callable[[Path], np.ndarray] | None = None
    max_depth: float | None = None
    intrinsics: np.ndarray | None = None  # (T,3,3) where the dataset provides them

    @property
    def num_frames(self) -> int:
        return len(self.image_paths)

    def frames(self) -> np.ndarray:
        """uint8 (T,H,W,3) RGB."""
        images = []
        for path in self.image_paths:
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                raise UserError(f"cannot decode {path}; the {self.dataset} download is damaged, fetch it again")
            images.append(image[..., ::-1])
        return np.stack(images)

    def depths(self) -> np.ndarray:
        """float32 (T,H,W) ground-truth depth (0 where unknown or beyond `max_depth`)."""
        if self.depth_paths is None or self.read_depth is None:
            raise UserError(f"{self.dataset} sequence {self.name} has no ground-truth depth in this layout")
        depth = np.stack([self.read_depth(p) for p in self.depth_paths]).astype(np.float32)
        if self.max_depth is not None:
            depth[depth >= self.max_depth] = 0
        return depth


# ----------------------------------------------------------------------------- file readers


def read_png_depth(path: Path, scale: float) -> np.ndarray:
    """16-bit PNG depth divided by `scale` (float32 (H,W); 0 stays 0 = invalid)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None or raw.ndim != 2:
        raise UserError(f"cannot read depth image {path} (expected a single-channel 16-bit PNG)")
    return raw.astype(np.float32) / scale


def read_sintel_depth(path: Path) -> np.ndarray:
    """Sintel .dpt: float32 tag 202021.25, int32 width, int32 height, float32 depth row-major."""
    with open(path, "rb") as f:
        tag = np.fromfile(f, np.float32, 1)
        size = np.fromfile(f, np.int32, 2)
        if len(tag) != 1 or tag[0] != SINTEL_TAG or len(size) != 2:
            raise UserError(f"{path} is not a Sintel .dpt depth file (bad tag); fetch the depth set again")
        width, height = int(size[0]), int(size[1])
        depth = np.fromfile(f, np.float32, width * height)
    if depth.size != width * height:
        raise UserError(f"{path} is truncated ({depth.size} of {width * height} values)")
    return depth.reshape(height, width)


def read_sintel_camera(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Sintel .cam: tag, then K (3x3) and world-to-camera [R|t] (3x4), float64 row-major."""
    with open(path, "rb") as f:
        tag = np.fromfile(f, np.float32, 1)
        values = np.fromfile(f, np.float64, 21)
    if len(tag) != 1 or tag[0] != SINTEL_TAG or values.size != 21:
        raise UserError(f"{path} is not a Sintel .cam file; fetch the camera data set again")
    world_to_cam = np.eye(4)
    world_to_cam[:3] = values[9:].reshape(3, 4)
    return values[:9].reshape(3, 3), world_to_cam


def _images(folder: Path) -> list[Path]:
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)  # zero-padded names


def _require(path: Path, dataset: str, layout: str) -> Path:
    if not path.exists():
        raise UserError(f"{dataset}: {path} does not exist; expected the layout {layout} "
                        "(see c4d_pipeline/eval_datasets.py)")
    return path


def _pick(found: list[str], wanted, dataset: str) -> list[str]:
    if wanted is None:
        return found
    missing = sorted(set(wanted) - set(found))
    if missing:
        raise UserError(f"{dataset}: sequences {missing} are not in the dataset folder (found: {found})")
    return [s for s in found if s in set(wanted)]


def associate(stamps_a: np.ndarray, stamps_b: np.ndarray, max_diff: float = 0.02) -> list[tuple[int, int]]:
    """TUM association: greedily match timestamps closest first, each used once, |a - b| < max_diff.
    Returns index pairs (ia, ib) sorted by ia."""
    diff = np.abs(stamps_a[:, None] - stamps_b[None, :])  # (A,B)
    candidates = np.argwhere(diff < max_diff)
    order = np.argsort(diff[candidates[:, 0], candidates[:, 1]], kind="stable")
    used_a, used_b, pairs = set(), set(), []
    for ia, ib in candidates[order]:
        if ia not in used_a and ib not in used_b:
            used_a.add(ia)
            used_b.add(ib)
            pairs.append((int(ia), int(ib)))
    return sorted(pairs)


def read_tum_trajectory(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Timestamps (N,) and camera-to-world poses (N,4,4) of a TUM file `t tx ty tz qx qy qz qw`."""
    return np.loadtxt(path, ndmin=2)[:, 0], read_tum(path)


def _read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """TUM list file `timestamp filename` -> timestamps (N,), filenames."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip() and not line.startswith("#")]
    try:
        return np.array([float(r[0]) for r in rows]), [r[1] for r in rows]
    except (IndexError, ValueError) as exc:
        raise UserError(f"{path} is not a TUM list file (lines 'timestamp filename')") from exc


# ----------------------------------------------------------------------------- datasets


def load_sintel(root: str | Path, sequences=None, render_pass: str = "final") -> list[EvalSequence]:
    """MPI Sintel training sequences with depth and cameras (all frames, depth capped at 70)."""
    layout = "ROOT/training/{final,depth,camdata_left}/SEQ/..."
    images_root = _require(Path(root) / "training" / render_pass, "Sintel", layout)
    cams_root = _require(Path(root) / "training" / "camdata_left", "Sintel", layout)
    depth_root = Path(root) / "training" / "depth"
    out = []
    for name in _pick(sorted(p.name for p in images_root.iterdir() if p.is_dir()), sequences, "Sintel"):
        images = _images(images_root / name)
        cams = sorted(_require(cams_root / name, "Sintel", layout).glob("*.cam"))
        if len(cams) != len(images):
            raise UserError(f"Sintel {name}: {len(images)} frames but {len(cams)} .cam files; the download is incomplete")
        K, world_to_cam = zip(*(read_sintel_camera(c) for c in cams))
        cam_to_world = np.stack([invert_pose(m) for m in world_to_cam])
        cam_to_world[:, :3, 3] -= cam_to_world[:, :3, 3].mean(axis=0)
        depths = sorted((depth_root / name).glob("*.dpt")) if (depth_root / name).is_dir() else None
        out.append(EvalSequence("sintel", name, images, depths, cam_to_world, read_sintel_depth, 70.0,
                                np.stack(K).astype(np.float32)))
    return out


def load_tum_dynamics(root: str | Path, sequences=None, stride: int = 3, count: int = 90) -> list[EvalSequence]:
    """TUM RGB-D fr3 dynamic sequences: associated rgb/pose frames, every 3rd, the first 90."""
    root = Path(root)
    found = sorted(p.name for p in _require(root, "TUM", "ROOT/SEQ/...").iterdir()
                   if (p / "rgb.txt").is_file() or (p / "rgb_90").is_dir())
    if not found:
        raise UserError(f"TUM: no sequence under {root} has rgb.txt + groundtruth.txt or rgb_90/ + "
                        "groundtruth_90.txt; pass the folder holding rgbd_dataset_freiburg3_* folders")
    out = []
    for name in _pick(found, sequences, "TUM"):
        seq = root / name
        if (seq / "rgb_90").is_dir():  # already prepared by MonST3R's prepare_tum.py
            images = _images(seq / "rgb_90")
            _, poses = read_tum_trajectory(_require(seq / "groundtruth_90.txt", "TUM", "SEQ/rgb_90 + SEQ/groundtruth_90.txt"))
        else:
            stamps, files = _read_file_list(seq / "rgb.txt")
            gt_stamps, gt_poses = read_tum_trajectory(_require(seq / "groundtruth.txt", "TUM", "SEQ/groundtruth.txt"))
            matches = associate(stamps, gt_stamps)[::stride][:count]
            images = [seq / files[i] for i, _ in matches]
            poses = gt_poses[[j for _, j in matches]]
        if len(poses) != len(images):
            raise UserError(f"TUM {name}: {len(images)} frames but {len(poses)} poses")
        out.append(EvalSequence("tum", name, images, None, poses,
                                intrinsics=np.repeat(TUM_FR3_INTRINSICS[None], len(images), 0)))
    return out


def load_scannet(root: str | Path, sequences=None, stride: int = 3, count: int = 90) -> list[EvalSequence]:
    """ScanNet scenes exported by the .sens reader: frames 0, 3, ..., 267 (first 90 at stride 3)."""
    layout = "ROOT/sceneXXXX_XX/{color/N.jpg,depth/N.png,pose/N.txt}"
    root = _require(Path(root), "ScanNet", layout)
    found = sorted(p.name for p in root.iterdir() if (p / "color").is_dir())
    if not found:
        raise UserError(f"ScanNet: no scene folder with color/ under {root}; expected {layout}")
    out = []
    for name in _pick(found, sequences, "ScanNet"):
        scene = root / name
        indices = sorted(int(p.stem) for p in (scene / "color").glob("*.jpg"))[: stride * count : stride]
        images = [scene / "color" / f"{i}.jpg" for i in indices]
        poses = np.stack([np.loadtxt(_require(scene / "pose" / f"{i}.txt", "ScanNet", layout)).reshape(4, 4)
                          for i in indices])
        depths = [scene / "depth" / f"{i}.png" for i in indices] if (scene / "depth").is_dir() else None
        out.append(EvalSequence("scannet", name, images, depths, poses, lambda p: read_png_depth(p, 1000.0)))
    return out


def load_bonn(root: str | Path, sequences=None, first: int = 30, last: int = 140) -> list[EvalSequence]:
    """Bonn RGB-D dynamic sequences: frames [30, 140) of rgb/ and depth/, depth capped at 70."""
    layout = "ROOT/rgbd_bonn_SEQ/{rgb/,depth/,groundtruth.txt}"
    root = _require(Path(root), "Bonn", layout)
    found = sorted(p.name.removeprefix("rgbd_bonn_") for p in root.glob("rgbd_bonn_*") if (p / "rgb").is_dir())
    if not found:
        raise UserError(f"Bonn: no rgbd_bonn_* folder with rgb/ under {root}; expected {layout}")
    out = []
    for name in _pick(found, sequences, "Bonn"):
        seq = root / f"rgbd_bonn_{name}"
        images = _images(seq / "rgb")[first:last]
        depths = _images(_require(seq / "depth", "Bonn", layout))[first:last]
        if len(depths) != len(images):
            raise UserError(f"Bonn {name}: {len(images)} frames but {len(depths)} depth images")
        poses = None
        if (seq / "groundtruth.txt").is_file():
            gt_stamps, gt_poses = read_tum_trajectory(seq / "groundtruth.txt")
            try:  # frames are named by their timestamps, as in TUM
                matches = associate(np.array([float(p.stem) for p in images]), gt_stamps)
            except ValueError:
                matches = []
            if len(matches) == len(images):
                poses = gt_poses[[j for _, j in matches]]
        out.append(EvalSequence("bonn", name, images, depths, poses, lambda p: read_png_depth(p, 5000.0), 70.0))
    return out


def load_kitti(root: str | Path, sequences=None, count: int = 110) -> list[EvalSequence]:
    """KITTI depth validation drives (gathered layout of MonST3R's prepare_kitti.py): first 110."""
    base = Path(root) / "depth_selection" / "val_selection_cropped"
    layout = "ROOT/depth_selection/val_selection_cropped/{image_gathered,groundtruth_depth_gathered}/DRIVE_02/"
    images_root = _require(base / "image_gathered", "KITTI", layout)
    depth_root = _require(base / "groundtruth_depth_gathered", "KITTI", layout)
    out = []
    for name in _pick(sorted(p.name for p in images_root.iterdir() if p.is_dir()), sequences, "KITTI"):
        images = _images(images_root / name)[:count]
        depths = _images(_require(depth_root / name, "KITTI", layout))[:count]
        if len(depths) != len(images):
            raise UserError(f"KITTI {name}: {len(images)} frames but {len(depths)} depth maps")
        out.append(EvalSequence("kitti", name, images, depths, None, lambda p: read_png_depth(p, 256.0)))
    return out


LOADERS = {"sintel": load_sintel, "tum": load_tum_dynamics, "scannet": load_scannet,
           "bonn": load_bonn, "kitti": load_kitti}


def load_eval_dataset(name: str, root: str | Path, sequences=None) -> list[EvalSequence]:
    """Sequences of benchmark `name` (sintel | tum | scannet | bonn | kitti) under `root`."""
    if name not in LOADERS:
        raise UserError(f"unknown dataset {name!r}; choose one of {', '.join(LOADERS)}")
    return LOADERS[name](root, sequences)
