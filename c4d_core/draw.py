"""Pictures of labels and tracks: colourised depth, flow and segmentation, track overlays, layouts.

numpy and OpenCV only (the floor never imports torch), so every package draws with the same code;
writing pictures and videos to files is `c4d_core.video`.
Images are RGB uint8 throughout: (H,W,3) for one picture, (T,H,W,3) for a video.

Track overlays (`draw_tracks`) colour each point by its mobility, in exactly the legend's colours:
    static  -> STATIC_COLOR (blue),  moving (probability > MOVING_THRESHOLD) -> MOVING_COLOR (red);
    a filled dot is visible, a hollow ring occluded.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence

import cv2
import numpy as np

from c4d_core.geometry import rescale_pixels

STATIC_COLOR = (40, 120, 255)  # RGB: points that stay put in the world
MOVING_COLOR = (255, 50, 40)  # RGB: points whose world position changes
TRACK_LEGEND = {"static": STATIC_COLOR, "moving": MOVING_COLOR}
MOVING_THRESHOLD = 0.5  # a predicted mobility probability above this is drawn as moving
BACKGROUND_SEGMENT_COLOR = (60, 60, 60)  # RGB of segmentation id 0 (floor, dome)
INVALID_COLOR = (0, 0, 0)  # RGB of pixels without a valid value (depth <= 0, NaN)
OUTLINE_COLOR = (20, 20, 20)  # RGB rim around track dots

_SUBPIXEL_BITS = 4  # cv2 drawing with fractional coordinates: positions scaled by 2**4
_FONT = cv2.FONT_HERSHEY_SIMPLEX


# --------------------------------------------------------------------------------------------
# Colour maps
# --------------------------------------------------------------------------------------------


def _finite_range(values: np.ndarray, percentiles: tuple[float, float]) -> tuple[float, float]:
    """Robust (low, high) of the finite entries; (0, 1) when there are none."""
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        return 0.0, 1.0
    low, high = np.percentile(finite, percentiles)
    return float(low), float(max(high, low + 1e-6))


def colorize_depth(
    depth: np.ndarray,
    vmin: float | None = None,
    vmax: float | None = None,
    inverse: bool = True,
    colormap: int = cv2.COLORMAP_TURBO,
) -> np.ndarray:
    """Depth (...,H,W) float in scene units -> RGB uint8 (...,H,W,3).

    One range for the whole array, so a video keeps its colours over time: by default the 2nd to
    98th percentile of valid values. With `inverse` (default) near is red and far blue, plotting
    1/depth the way disparity maps are shown. Pixels with depth <= 0 or not finite are black.
    """
    depth = np.asarray(depth, dtype=np.float32)
    valid = np.isfinite(depth) & (depth > 0)
    safe = np.where(valid, depth, 1.0)
    values = np.where(valid, 1.0 / safe if inverse else safe, np.nan)
    if vmin is not None and vmax is not None:
        low, high = (1.0 / vmax, 1.0 / vmin) if inverse else (vmin, vmax)
    else:
        low, high = _finite_range(values, (2.0, 98.0))
    scaled = np.clip((values - low) / (high - low), 0.0, 1.0)
    if not inverse:
        scaled = 1.0 - scaled  # near stays red either way
    gray = np.nan_to_num(scaled * 255.0, nan=0.0).astype(np.uint8)
    flat = gray.reshape(-1, gray.shape[-1])  # applyColorMap wants 2-D
    rgb = cv2.applyColorMap(flat, colormap)[..., ::-1].reshape(*gray.shape, 3)
    rgb = np.ascontiguousarray(rgb)
    rgb[~valid] = INVALID_COLOR
    return rgb


def _flow_color_wheel() -> np.ndarray:
    """The Middlebury optical-flow colour wheel (Baker et al. 2007): (55, 3) float RGB in [0, 1].

    Hue segments red->yellow->green->cyan->blue->magenta->red with 15, 6, 4, 11, 13, 6 steps,
    spaced so perceptually similar directions get similar colours.
    """
    segments = [(15, (1, 0, 0), (1, 1, 0)), (6, (1, 1, 0), (0, 1, 0)), (4, (0, 1, 0), (0, 1, 1)),
                (11, (0, 1, 1), (0, 0, 1)), (13, (0, 0, 1), (1, 0, 1)), (6, (1, 0, 1), (1, 0, 0))]
    rows = []
    for steps, start, end in segments:
        frac = np.arange(steps)[:, None] / steps  # (steps,1)
        rows.append((1 - frac) * np.array(start) + frac * np.array(end))
    return np.concatenate(rows).astype(np.float32)


_WHEEL = _flow_color_wheel()


def colorize_flow(flow: np.ndarray, max_magnitude: float | None = None) -> np.ndarray:
    """Optical flow (...,H,W,2) as (dx, dy) pixels -> RGB uint8 (...,H,W,3) on the standard wheel.

    Direction is hue, magnitude is saturation: zero flow is white, flow of `max_magnitude`
    fully saturated, longer vectors darkened. The default `max_magnitude` is the 99th percentile
    of the whole array's magnitudes, so one fast object does not wash out the camera's flow.
    Non-finite vectors are black.
    """
    flow = np.asarray(flow, dtype=np.float32)
    dx, dy = flow[..., 0], flow[..., 1]
    valid = np.isfinite(dx) & np.isfinite(dy)
    dx, dy = np.where(valid, dx, 0.0), np.where(valid, dy, 0.0)
    magnitude = np.hypot(dx, dy)
    if max_magnitude is None:
        max_magnitude = float(np.percentile(magnitude, 99)) if magnitude.size else 0.0
    radius = magnitude / max(max_magnitude, 1e-6)

    n = len(_WHEEL)
    position = (np.arctan2(-dy, -dx) / np.pi + 1.0) / 2.0 * (n - 1)  # angle -> [0, n-1]
    i0 = np.floor(position).astype(np.int64)
    i1 = (i0 + 1) % n
    frac = (position - i0)[..., None]
    color = (1 - frac) * _WHEEL[i0] + frac * _WHEEL[i1]  # (...,3) fully saturated hue
    inside = (radius <= 1.0)[..., None]
    r = radius[..., None]
    color = np.where(inside, 1.0 - r * (1.0 - color), color * 0.75)
    rgb = np.round(color * 255.0).astype(np.uint8)
    rgb[~valid] = INVALID_COLOR
    return rgb


def segment_palette(num_ids: int) -> np.ndarray:
    """Stable colours for segment ids 0..num_ids-1: uint8 (num_ids, 3) RGB.

    Id 0 (background) is dark grey; id k > 0 steps the hue by the golden ratio, so neighbouring
    ids differ strongly and an id keeps its colour whatever the number of objects.
    """
    palette = np.empty((max(num_ids, 1), 3), dtype=np.uint8)
    palette[0] = BACKGROUND_SEGMENT_COLOR
    for k in range(1, num_ids):
        hue = (k * 0.618033988749895) % 1.0
        value = 0.95 if k % 2 else 0.75
        palette[k] = np.round(np.array(colorsys.hsv_to_rgb(hue, 0.8, value)) * 255)
    return palette


def colorize_segmentation(segmentation: np.ndarray) -> np.ndarray:
    """Integer ids (...,H,W) -> RGB uint8 (...,H,W,3) with `segment_palette` (negative ids black)."""
    segmentation = np.asarray(segmentation)
    ids = segmentation.astype(np.int64)
    palette = segment_palette(int(ids.max()) + 1 if ids.size else 1)
    rgb = palette[np.clip(ids, 0, None)]
    rgb[ids < 0] = INVALID_COLOR
    return rgb


def colorize_mask(mask: np.ndarray, color: Sequence[int] = MOVING_COLOR) -> np.ndarray:
    """Boolean or [0,1] mask (...,H,W) -> RGB uint8 (...,H,W,3): black where 0, `color` where 1."""
    weight = np.asarray(mask, dtype=np.float32)[..., None]
    return np.round(weight * np.asarray(color, dtype=np.float32)).astype(np.uint8)


def blend(image: np.ndarray, overlay: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """Mix two RGB uint8 arrays of equal shape: (1 - alpha) * image + alpha * overlay."""
    mixed = (1.0 - alpha) * image.astype(np.float32) + alpha * overlay.astype(np.float32)
    return np.round(mixed).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Track overlays
# --------------------------------------------------------------------------------------------


def track_colors(moving: np.ndarray) -> np.ndarray:
    """Mobility (T,N) bool or probability in [0,1] -> RGB float (T,N,3): MOVING_COLOR where it is
    above MOVING_THRESHOLD, STATIC_COLOR elsewhere (NaN too), so every dot has a legend colour."""
    is_moving = (np.nan_to_num(np.asarray(moving, dtype=np.float32)) > MOVING_THRESHOLD)[..., None]
    return np.where(is_moving, np.asarray(MOVING_COLOR, np.float32), np.asarray(STATIC_COLOR, np.float32))


def _identity_colors(num_tracks: int) -> np.ndarray:
    """One fixed colour per track, for overlays without a mobility label: (N,3) float RGB."""
    return segment_palette(num_tracks + 1)[1:].astype(np.float32)


def _fixed(points: np.ndarray) -> np.ndarray:
    """(..., 2) float pixel coordinates -> int coordinates for cv2's sub-pixel drawing."""
    return np.round(points * (1 << _SUBPIXEL_BITS)).astype(np.int64)


def draw_tracks(
    frames: np.ndarray,
    tracks: np.ndarray,
    visible: np.ndarray | None = None,
    moving: np.ndarray | None = None,
    show_occluded: bool = True,
    trail: int = 0,
    radius: float | None = None,
    legend: bool = False,
) -> np.ndarray:
    """Draw point tracks on a video; returns a new RGB uint8 (T,H,W,3), `frames` is not changed.

    Layout is time first, like the tracker's output: `tracks` float (T,N,2) as (x, y) pixels with
    pixel centres at integer coordinates; `visible` bool (T,N) (default all visible); `moving`
    (T,N) bool or probability (default None: one fixed colour per track instead of mobility).
    A `Scene` stores tracks as (N,T,2): `scene.tracks_time_major()` gives this layout.

    Visible points are filled dots with a dark rim; occluded points are hollow rings, or left out
    when `show_occluded` is False. `trail` > 0 draws each track's last `trail` visible steps as a
    polyline. `radius` defaults to about 1% of the image diagonal. `legend` adds the colour key in
    a strip below the frames (the output is then taller than `frames`).
    """
    frames = np.asarray(frames)
    tracks = np.asarray(tracks, dtype=np.float32)
    num_frames, height, width = frames.shape[:3]
    if tracks.ndim != 3 or tracks.shape[0] != num_frames or tracks.shape[2] != 2:
        raise ValueError(f"tracks must be (T={num_frames},N,2), got {tracks.shape}")
    num_tracks = tracks.shape[1]
    visible = np.ones((num_frames, num_tracks), bool) if visible is None else np.asarray(visible, bool)
    if moving is None:
        colors = np.broadcast_to(_identity_colors(num_tracks), (num_frames, num_tracks, 3))
    else:
        colors = track_colors(moving)  # (T,N,3)
    if radius is None:
        radius = max(1.5, 0.01 * float(np.hypot(height, width)))
    r_fixed = int(round(radius * (1 << _SUBPIXEL_BITS)))
    outline = int(round(max(1.0, radius / 3) * (1 << _SUBPIXEL_BITS)))
    finite = np.isfinite(tracks).all(axis=-1)  # (T,N)
    fixed = _fixed(np.where(finite[..., None], tracks, 0.0))  # (T,N,2)

    out = np.ascontiguousarray(frames.copy())
    for t in range(num_frames):
        canvas = out[t]
        if trail > 0:
            start = max(0, t - trail)
            for n in range(num_tracks):
                keep = visible[start : t + 1, n] & finite[start : t + 1, n]
                if keep.sum() < 2:
                    continue
                color = tuple(float(c) for c in colors[t, n])
                pts = fixed[start : t + 1, n][keep].reshape(-1, 1, 2).astype(np.int32)
                cv2.polylines(canvas, [pts], False, color, 1, cv2.LINE_AA, _SUBPIXEL_BITS)
        for n in range(num_tracks):
            if not finite[t, n] or (not visible[t, n] and not show_occluded):
                continue
            center = (int(fixed[t, n, 0]), int(fixed[t, n, 1]))
            color = tuple(float(c) for c in colors[t, n])
            if visible[t, n]:  # a dark rim first, so the dot shows on light and dark floors alike
                cv2.circle(canvas, center, r_fixed + outline, OUTLINE_COLOR, -1, cv2.LINE_AA, _SUBPIXEL_BITS)
                cv2.circle(canvas, center, r_fixed, color, -1, cv2.LINE_AA, _SUBPIXEL_BITS)
            else:
                cv2.circle(canvas, center, r_fixed, OUTLINE_COLOR, 3, cv2.LINE_AA, _SUBPIXEL_BITS)
                cv2.circle(canvas, center, r_fixed, color, 1, cv2.LINE_AA, _SUBPIXEL_BITS)
    if legend and moving is not None:
        out = np.stack([draw_legend(frame, TRACK_LEGEND) for frame in out])
    return out


def draw_tracks_enlarged(
    frames: np.ndarray, tracks: np.ndarray, visible: np.ndarray | None = None,
    moving: np.ndarray | None = None, min_height: int = 256, **kwargs,
) -> np.ndarray:
    """`draw_tracks` on frames enlarged by the integer factor that brings them to `min_height` rows.

    Small videos (a 64x64 demo scene) stay legible: dots and the legend are drawn at the display
    size and tracks are moved to the enlarged pixel grid (x' = (x + 0.5) f - 0.5). Same arguments
    as `draw_tracks`; returns RGB uint8 (T,H*f,W*f,3).
    """
    factor = display_scale(np.asarray(frames).shape[1], min_height)
    tracks = rescale_pixels(np.asarray(tracks, dtype=np.float32), factor)
    return draw_tracks(upscale(np.asarray(frames), factor), tracks, visible, moving, **kwargs)


def draw_legend(image: np.ndarray, entries: dict[str, Sequence[int]]) -> np.ndarray:
    """An RGB image (H,W,3) with a colour key (name -> RGB) in a strip below it, not over it:
    (H + strip, W, 3)."""
    return np.concatenate([image, key_strip(image.shape[1], entries)], axis=0)


def key_strip(width: int, entries: dict[str, Sequence[int]] | None = None, depth: bool = False,
              flow: bool = False, height: int = 26) -> np.ndarray:
    """A dark strip (height, width, 3) of colour keys to place under a picture: the named colours
    (a square each), a near-to-far bar of `colorize_depth`'s colours and the flow colour wheel
    (direction = hue, speed = saturation) where asked. Keys that do not fit are left out."""
    strip = np.full((height, width, 3), 32, np.uint8)
    scale, x = 0.4, 6
    baseline = height // 2 + 5

    def text(label: str) -> None:
        nonlocal x
        cv2.putText(strip, label, (x, baseline), _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)
        x += cv2.getTextSize(label, _FONT, scale, 1)[0][0] + 10

    for name, color in (entries or {}).items():
        if x + 60 > width:
            break
        cv2.rectangle(strip, (x, 6), (x + height - 12, height - 7), tuple(int(c) for c in color), -1)
        x += height - 6
        text(name)
    if depth and x + 150 <= width:
        text("depth: near")
        ramp = colorize_depth(np.linspace(1.0, 4.0, 60, dtype=np.float32)[None].repeat(height - 12, 0),
                              vmin=1.0, vmax=4.0)
        strip[6:height - 6, x:x + 60] = ramp
        x += 66
        text("far")
    if flow and x + 120 <= width:
        size = height - 4
        v, u = np.mgrid[:size, :size].astype(np.float32) - (size - 1) / 2
        wheel = colorize_flow(np.stack([u, v], -1), max_magnitude=(size - 1) / 2)
        wheel[np.hypot(u, v) > (size - 1) / 2] = strip[0, 0]
        strip[2:2 + size, x:x + size] = wheel
        x += size + 6
        text("flow: hue = direction")
    return strip


def title_strip(width: int, text: str, height: int = 26) -> np.ndarray:
    """A dark strip (height, width, 3) with `text` in white, shrunk to fit, to place above a picture."""
    strip = np.full((height, width, 3), 32, np.uint8)
    scale = min(0.5, 0.5 * (width - 12) / max(1, cv2.getTextSize(text, _FONT, 0.5, 1)[0][0]))
    cv2.putText(strip, text, (6, height // 2 + 5), _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return strip


def draw_axes(image: np.ndarray, origin: np.ndarray, tips: np.ndarray, names: Sequence[str],
              colors: Sequence[Sequence[int]]) -> None:
    """Draw axes in place on an RGB image (H,W,3): a 2-pixel line from `origin` (2,) to each of
    `tips` (K,2), pixel (x, y), in `colors[k]` (RGB, unblended) with `names[k]` just past its tip."""
    origin = np.asarray(origin, np.float64)
    start = tuple(int(round(c)) for c in origin)
    for tip, name, color in zip(np.asarray(tips, np.float64), names, colors):
        color = tuple(int(c) for c in color)
        cv2.line(image, start, tuple(int(round(c)) for c in tip), color, 2, cv2.LINE_8)
        (width, height), _ = cv2.getTextSize(name, _FONT, 0.6, 2)
        direction = (tip - origin) / max(float(np.linalg.norm(tip - origin)), 1e-6)
        center = tip + (6 + max(width, height) / 2) * direction  # beyond the tip, off the line
        label = (int(round(center[0] - width / 2)), int(round(center[1] + height / 2)))
        cv2.putText(image, name, label, _FONT, 0.6, OUTLINE_COLOR, 4, cv2.LINE_AA)  # readable on any points
        cv2.putText(image, name, label, _FONT, 0.6, color, 2, cv2.LINE_AA)


# --------------------------------------------------------------------------------------------
# Layout
# --------------------------------------------------------------------------------------------


def _put_text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float) -> None:
    """White text on a black box, readable on any background (in place). `origin`: bottom-left."""
    thickness = max(1, int(round(scale * 1.5)))
    (width, height), baseline = cv2.getTextSize(text, _FONT, scale, thickness)
    x, y = origin
    cv2.rectangle(image, (x - 2, y - height - 2), (x + width + 1, y + baseline), (0, 0, 0), -1)
    cv2.putText(image, text, origin, _FONT, scale, (255, 255, 255), thickness, cv2.LINE_AA)


def label_image(image: np.ndarray, text: str) -> np.ndarray:
    """Copy of an RGB image (H,W,3) with `text` written in its top-left corner."""
    out = np.ascontiguousarray(image.copy())
    scale = max(0.35, min(image.shape[0], image.shape[1]) / 500.0)
    _put_text(out, text, (4, 4 + int(round(22 * scale))), scale)
    return out


def display_scale(height: int, min_height: int) -> int:
    """Smallest integer factor that brings an image of `height` rows to at least `min_height`."""
    return max(1, int(np.ceil(min_height / height)))


def upscale(images: np.ndarray, factor: int) -> np.ndarray:
    """Nearest-neighbour enlargement by an integer factor: (...,H,W,C) -> (...,H*f,W*f,C)."""
    if factor == 1:
        return images
    return images.repeat(factor, axis=-3).repeat(factor, axis=-2)


def _resize_to_height(image: np.ndarray, height: int) -> np.ndarray:
    if image.shape[-3] == height:
        return image
    width = max(1, int(round(image.shape[-2] * height / image.shape[-3])))
    if image.ndim == 3:
        return cv2.resize(image, (width, height), interpolation=cv2.INTER_NEAREST)
    return np.stack([cv2.resize(f, (width, height), interpolation=cv2.INTER_NEAREST) for f in image])


def side_by_side(
    panels: Sequence[np.ndarray], labels: Sequence[str] | None = None, gap: int = 2
) -> np.ndarray:
    """Place RGB panels left to right: all (H,W,3) images or all (T,H,W,3) videos of equal T.

    Panels are scaled (nearest neighbour) to the first panel's height and separated by `gap`
    white pixels; `labels` are written on them. Returns uint8 (H,W',3) or (T,H,W',3).
    """
    if not panels:
        raise ValueError("side_by_side needs at least one panel")
    height = panels[0].shape[-3]
    scaled = [_resize_to_height(np.asarray(p, np.uint8), height) for p in panels]
    if labels is not None:
        scaled = [
            np.stack([label_image(f, text) for f in p]) if p.ndim == 4 else label_image(p, text)
            for p, text in zip(scaled, labels)
        ]
    spacer_shape = (*scaled[0].shape[:-2], gap, 3)
    pieces = []
    for i, panel in enumerate(scaled):
        if i and gap:
            pieces.append(np.full(spacer_shape, 255, np.uint8))
        pieces.append(panel)
    return np.concatenate(pieces, axis=-2)


def contact_sheet(
    images: Sequence[np.ndarray] | np.ndarray,
    columns: int | None = None,
    labels: Sequence[str] | None = None,
    gap: int = 2,
) -> np.ndarray:
    """Grid of equally sized RGB images (N,H,W,3) -> one uint8 image, row by row, white gaps.

    `columns` defaults to ceil(sqrt(N)); `labels` (N strings) are written on the tiles.
    """
    images = [np.asarray(i, np.uint8) for i in images]
    if not images:
        raise ValueError("contact_sheet needs at least one image")
    if labels is not None:
        images = [label_image(i, text) for i, text in zip(images, labels)]
    count = len(images)
    columns = columns or int(np.ceil(np.sqrt(count)))
    rows = int(np.ceil(count / columns))
    h, w = images[0].shape[:2]
    sheet = np.full((rows * h + (rows - 1) * gap, columns * w + (columns - 1) * gap, 3), 255, np.uint8)
    for i, image in enumerate(images):
        r, c = divmod(i, columns)
        sheet[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = image
    return sheet
