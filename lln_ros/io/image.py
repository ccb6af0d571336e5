"""Image checks, loading and the resize every extraction starts with.

Images are numpy uint8 arrays, (H, W) grey or (H, W, C) with C in {1, 3, 4}; the channel order of
colour images is named by the caller ('rgb' or 'bgr'; a fourth channel is alpha and dropped).
"""

from __future__ import annotations

import os

import cv2
import numpy as np

from ..errors import ImageError

MIN_SIDE = 8  # below this there is no structure left to upsample into a 32-pixel grid cell
MAX_WIDTH = 4096  # after resizing to the input height: guards against absurd aspect ratios
GRID_STRIDE = 32  # every backbone here has a stride-32 feature grid


def check_image(image, channel_order: str = 'rgb') -> np.ndarray:
    """Validate an image and return it as RGB uint8 (H, W, 3). Raises ImageError naming the problem."""
    if not isinstance(image, np.ndarray):
        raise ImageError(f'image must be a numpy array, got {type(image).__name__}')
    if image.dtype != np.uint8:
        raise ImageError(f'image dtype must be uint8, got {image.dtype}')
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (3, 4)):
        raise ImageError(f'image must be (H, W) grey or (H, W, 3|4) colour, got shape {image.shape}')
    h, w = image.shape[:2]
    if h < MIN_SIDE or w < MIN_SIDE:
        raise ImageError(f'image is {w}x{h} pixels; both sides must be at least {MIN_SIDE}')
    if channel_order not in ('rgb', 'bgr'):
        raise ImageError(f"channel_order must be 'rgb' or 'bgr', got {channel_order!r}")
    if image.ndim == 2:
        return np.ascontiguousarray(np.repeat(image[:, :, None], 3, axis=2))
    image = image[:, :, :3]
    if channel_order == 'bgr':
        image = image[:, :, ::-1]
    return np.ascontiguousarray(image)


def network_size(width: int, height: int, input_height: int) -> tuple[int, int]:
    """(width, height) fed to the network: height = input_height, aspect kept, and the width
    rounded to a multiple of the grid stride so every grid cell covers whole network pixels."""
    if input_height < GRID_STRIDE or input_height % GRID_STRIDE:
        raise ImageError(f'input_height must be a positive multiple of {GRID_STRIDE}, got {input_height}')
    net_w = max(GRID_STRIDE, int(round(width * input_height / height / GRID_STRIDE)) * GRID_STRIDE)
    if net_w > MAX_WIDTH:
        raise ImageError(
            f'image aspect {width}x{height} gives a network width of {net_w} px at height '
            f'{input_height}; at most {MAX_WIDTH} is supported'
        )
    return net_w, input_height


def resize_for_network(rgb: np.ndarray, input_height: int) -> np.ndarray:
    """RGB uint8 (H, W, 3) -> RGB uint8 (input_height, W', 3). INTER_AREA when shrinking (no
    aliasing), INTER_LINEAR when enlarging (tiny images such as Nordland's 64x32 are upsampled)."""
    h, w = rgb.shape[:2]
    size = network_size(w, h, input_height)
    interp = cv2.INTER_AREA if size[1] < h else cv2.INTER_LINEAR
    return cv2.resize(rgb, size, interpolation=interp)


def load_image(path: str) -> np.ndarray:
    """Read an image file as RGB uint8 (H, W, 3)."""
    if os.path.isdir(path):
        raise ImageError(f'{path!r} is a directory, not an image file')
    if not os.path.isfile(path):
        raise ImageError(f'image file not found: {path!r}')
    bgr = cv2.imread(path, cv2.IMREAD_COLOR)
    if bgr is None:
        raise ImageError(f'cannot decode image file {path!r} (not an image, or truncated)')
    return check_image(bgr, 'bgr')


def photo_views(count: int, width: int, height: int = 288, sample: str = 'grace_hopper.jpg') -> list[np.ndarray]:
    """`count` different views (width x height, RGB uint8) of a photograph that ships with matplotlib
    (an exec dependency, so every install has it): crops of the size's aspect, shifted and every
    second one mirrored, resized so the network sees them as they are. The benchmarks' frames and
    the int8 runtime's calibration images (core.runtime)."""
    import matplotlib.cbook as cbook

    with cbook.get_sample_data(sample) as f:
        photo = load_image(f.name)
    ph, pw = photo.shape[:2]
    cw = min(pw, int(ph * width / height)) * 9 // 10
    ch = int(cw * height / width)
    out = []
    for i in range(count):
        y, x = (i * 37) % max(1, ph - ch), (i * 53) % max(1, pw - cw)
        v = cv2.resize(photo[y : y + ch, x : x + cw], (width, height), interpolation=cv2.INTER_AREA)
        out.append(np.ascontiguousarray(v[:, ::-1] if i % 2 else v))
    return out


# ---------------------------------------------------------------------------------------- heatmaps
# OpenCV only (no matplotlib): the extractor node draws its `activation` image with these


def heatmap(activation: np.ndarray, size: tuple) -> np.ndarray:
    """Activation (rows, cols) -> float (H, W) in [0, 1], bilinearly upsampled to size=(W, H)."""
    a = np.asarray(activation, np.float32)
    span = float(a.max() - a.min())
    a = (a - a.min()) / span if span > 0 else np.zeros_like(a)
    return cv2.resize(a, tuple(int(v) for v in size), interpolation=cv2.INTER_LINEAR)


def heatmap_bgr(image_rgb: np.ndarray, activation: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """The image blended with a JET heatmap of its activation, as BGR uint8 (for ROS `activation`)."""
    h, w = image_rgb.shape[:2]
    heat = cv2.applyColorMap((heatmap(activation, (w, h)) * 255).astype(np.uint8), cv2.COLORMAP_JET)
    return cv2.addWeighted(cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), 1 - alpha, heat, alpha, 0)
