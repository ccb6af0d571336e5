"""The camera model and depth images registration needs, checked the way a robot's inputs must be.

    cam = CameraModel.from_camera_info('camera_info.yaml')   # or a CameraInfo-like dict / message
    cam.check_image(width, height)                           # CameraError when the image differs
    xy = cam.normalise(uv)                                   # (N, 2) pixels -> undistorted z=1 plane
    depth_m = depth_metres(array, '16UC1', (width, height))  # REP 118 -> (H, W) float32 metres, NaN = none

Sources: a camera_calibration_parsers YAML (image_width, image_height, camera_matrix.data,
distortion_model, distortion_coefficients.data), a sensor_msgs/CameraInfo as a dict or message
(width, height, k, d, distortion_model), or the path of such a YAML. A CameraInfo of an
uncalibrated camera is all zeros: refused, as are NaN, non-positive focal lengths, a principal point
outside the image and distortion coefficients the model does not define. Every refusal is a
lln_ros.errors.CameraError naming the value.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..errors import CameraError

# distortion_model (sensor_msgs/distortion_models.h) -> coefficient counts OpenCV accepts for it
DISTORTION_MODELS = {'plumb_bob': (5,), 'rational_polynomial': (8, 12, 14), 'equidistant': (4,), '': (0,)}
# REP 118 depth encodings: 16UC1 is millimetres (0 = no reading), 32FC1 metres (NaN or 0 = none)
DEPTH_ENCODINGS = {'16UC1': (np.uint16, 1e-3), 'mono16': (np.uint16, 1e-3), '32FC1': (np.float32, 1.0)}


@dataclass(frozen=True)
class CameraModel:
    """Pinhole camera with optional distortion. K (3, 3) float64, D (n,) float64 (n fixed by
    distortion_model, 0 = none), width, height in pixels, frame_id of the optical frame."""

    K: np.ndarray
    D: np.ndarray
    width: int
    height: int
    distortion_model: str = 'plumb_bob'
    frame_id: str = ''

    def __post_init__(self):
        k = np.asarray(self.K, np.float64)
        d = np.asarray(self.D, np.float64).ravel()
        object.__setattr__(self, 'K', k)
        object.__setattr__(self, 'D', d)
        check_intrinsics(k, d, self.width, self.height, self.distortion_model)

    @classmethod
    def from_camera_info(cls, source, frame_id: str = '') -> 'CameraModel':
        """From a camera_calibration YAML path or dict, or a sensor_msgs/CameraInfo (dict or message)."""
        if isinstance(source, (str, bytes)) or hasattr(source, '__fspath__'):
            source = load_yaml(source)
        if not isinstance(source, dict):  # a message object: its fields as a dict
            frame_id = frame_id or getattr(getattr(source, 'header', None), 'frame_id', '')
            source = {
                k: getattr(source, k) for k in ('width', 'height', 'k', 'd', 'distortion_model') if hasattr(source, k)
            }
        header = source.get('header')
        frame_id = (
            frame_id or source.get('frame_id') or (header.get('frame_id', '') if isinstance(header, dict) else '')
        )
        width = source.get('image_width', source.get('width'))
        height = source.get('image_height', source.get('height'))
        k = _field(source, ('camera_matrix', 'k', 'K'), 'camera matrix')
        d = _field(source, ('distortion_coefficients', 'd', 'D'), 'distortion coefficients', required=False)
        model = source.get('distortion_model', 'plumb_bob' if d is not None and len(d) else '')
        if width is None or height is None:
            raise CameraError('camera info needs image_width/image_height (or width/height)')
        try:
            width, height = int(width), int(height)
        except (TypeError, ValueError):
            raise CameraError(f'camera info size must be whole numbers, got {width!r} x {height!r}') from None
        if k is None or len(k) != 9:
            raise CameraError(f'camera matrix must hold 9 numbers (row-major 3x3 K), got {k!r:.80}')
        return cls(
            np.reshape(k, (3, 3)), np.zeros(0) if d is None else d, width, height, str(model or ''), str(frame_id)
        )

    def check_image(self, width: int, height: int) -> None:
        """CameraError unless an image of width x height is the one this calibration describes."""
        if (int(width), int(height)) != (self.width, self.height):
            raise CameraError(
                f'camera info is for {self.width}x{self.height} images, the image is {int(width)}x{int(height)}'
            )

    @property
    def focal(self) -> float:
        """Mean focal length in pixels: converts normalised residuals to pixels."""
        return 0.5 * (self.K[0, 0] + self.K[1, 1])

    def normalise(self, uv: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalised image coordinates (N, 2) float64 (z = 1 plane)."""
        uv = np.asarray(uv, np.float64).reshape(-1, 1, 2)
        if not len(uv):
            return np.zeros((0, 2))
        if self.distortion_model == 'equidistant' and np.any(self.D):
            return cv2.fisheye.undistortPoints(uv, self.K, self.D).reshape(-1, 2)
        return cv2.undistortPoints(uv, self.K, self.D if np.any(self.D) else None).reshape(-1, 2)

    def to_dict(self) -> dict:
        """The CameraInfo fields (width, height, k, d, distortion_model, frame_id), JSON-friendly."""
        return {
            'width': self.width,
            'height': self.height,
            'k': self.K.ravel().tolist(),
            'd': self.D.tolist(),
            'distortion_model': self.distortion_model,
            'frame_id': self.frame_id,
        }


def check_intrinsics(K: np.ndarray, D: np.ndarray, width, height, model: str) -> None:
    """CameraError unless K (3, 3), D (n,) and the size describe a calibrated camera."""
    if not (isinstance(width, (int, np.integer)) and isinstance(height, (int, np.integer)) and width > 0 < height):
        raise CameraError(f'camera image size must be positive whole numbers, got {width!r} x {height!r}')
    if K.shape != (3, 3):
        raise CameraError(f'camera matrix must be 3x3, got shape {K.shape}')
    if not np.isfinite(K).all() or not np.isfinite(D).all():
        raise CameraError(f'camera info holds NaN or infinity: K = {K.ravel().tolist()}, D = {D.tolist()}')
    if not K.any():
        raise CameraError('camera matrix is all zeros (an uncalibrated camera publishes that): calibrate it first')
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0):
        raise CameraError(f'focal lengths must be positive, got fx={fx}, fy={fy}')
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise CameraError(f'principal point ({cx}, {cy}) lies outside the {width}x{height} image: wrong size?')
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CameraError(f'camera matrix must be upper triangular with K[2,2] = 1, got {K.ravel().tolist()}')
    if model not in DISTORTION_MODELS:
        raise CameraError(f'unknown distortion_model {model!r}; supported: {sorted(m for m in DISTORTION_MODELS if m)}')
    if len(D) and len(D) not in DISTORTION_MODELS[model]:
        raise CameraError(f'distortion_model {model!r} takes {DISTORTION_MODELS[model]} coefficients, got {len(D)}')


def depth_metres(depth: np.ndarray, encoding: str, size=None) -> np.ndarray:
    """A depth image registered to the colour camera (REP 118) as (H, W) float32 metres, NaN where
    there is no reading (0 in 16UC1; 0, NaN or inf in 32FC1; negative values in either).
    size (width, height): the colour image's, which the depth image must match."""
    if encoding not in DEPTH_ENCODINGS:
        raise CameraError(f'depth encoding {encoding!r} is not a REP 118 depth image (use 16UC1 in mm or 32FC1 in m)')
    dtype, to_m = DEPTH_ENCODINGS[encoding]
    depth = np.asarray(depth)
    if depth.ndim == 3 and depth.shape[2] == 1:
        depth = depth[:, :, 0]
    if depth.ndim != 2 or not depth.size:
        raise CameraError(f'depth image must be one channel (H, W), got shape {depth.shape}')
    if depth.dtype != dtype:
        raise CameraError(f'depth encoding {encoding} needs {np.dtype(dtype).name} pixels, got {depth.dtype}')
    if size is not None and (depth.shape[1], depth.shape[0]) != (int(size[0]), int(size[1])):
        raise CameraError(
            f'depth image is {depth.shape[1]}x{depth.shape[0]}, the colour image {int(size[0])}x{int(size[1])} '
            '(depth must be registered to the colour camera)'
        )
    m = depth.astype(np.float32) * np.float32(to_m)
    m[~np.isfinite(m) | (m <= 0)] = np.nan
    return m


def _field(source: dict, keys, what: str, required: bool = True):
    for key in keys:
        if key in source:
            value = source[key]
            if isinstance(value, dict):
                value = value.get('data')
            try:
                return [float(v) for v in np.asarray(value, dtype=object).ravel()]
            except (TypeError, ValueError):
                raise CameraError(f'camera info {what} must be numbers, got {value!r:.80}') from None
    if required:
        raise CameraError(f'camera info has no {what} (one of {", ".join(keys)})')
    return None


def load_yaml(path, what: str = 'camera info', error: type = CameraError) -> dict:
    """A ROS camera-calibration YAML (camera_calibration / camera_info_manager layout) as a dict;
    `error` (naming the file as `what`) when it cannot be read, is not YAML or not a mapping."""
    import yaml

    try:
        with open(path) as f:
            data = yaml.safe_load(f)
    except OSError as e:
        raise error(f'cannot read {what} {str(path)!r}: {e.strerror}') from None
    except yaml.YAMLError as e:
        raise error(f'{what} {str(path)!r} is not valid YAML: {e}') from None
    if not isinstance(data, dict):
        raise error(f'{what} {str(path)!r} must be a YAML mapping')
    return data
