"""The keypoints table as sensor_msgs/PointCloud2 (the extractor's ORB keypoints for the matcher's
verify mode; layout in the package docstring and docs/interfaces.md §2.8)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ...errors import MessageError
from .clouds import _DATATYPES, KEYPOINT_FIELDS, array_to_cloud, check_fields, cloud_to_array

__all__ = ['keypoints_to_cloud', 'cloud_to_keypoints']


def keypoints_to_cloud(kps, header: Header | None = None) -> PointCloud2:
    """ORB keypoints of one image (reloc.Keypoints, 32-byte descriptors), published beside its
    landmarks with the same header; with kps.depth (N,) also a FLOAT32 depth field (metres, NaN = none)."""
    desc = np.asarray(kps.descriptors)
    if desc.dtype != np.uint8 or desc.ndim != 2 or desc.shape[1] != 32 or len(desc) != len(kps.uv):
        raise MessageError(f'keypoints cloud: descriptors must be uint8 (N, 32) (ORB), got {desc.dtype} {desc.shape}')
    depth = getattr(kps, 'depth', None)
    if depth is not None and np.shape(depth) != (len(desc),):
        raise MessageError(f'keypoints cloud: depth must be ({len(desc)},), got {np.shape(depth)}')
    table = np.zeros(
        len(desc),
        [(n, _DATATYPES[dt]) for n, dt, _ in KEYPOINT_FIELDS[:-1]]
        + [('descriptor', 'u1', (32,))]
        + [('depth', '<f4')] * (depth is not None),
    )
    table['u'], table['v'] = kps.uv[:, 0], kps.uv[:, 1]
    for name in ('size', 'angle', 'response', 'octave') + ('depth',) * (depth is not None):
        table[name] = getattr(kps, name)
    table['descriptor'] = desc
    return array_to_cloud(table, header)


def cloud_to_keypoints(msg: PointCloud2, image_size=(0, 0), scale: float = 1.0, max_rows: int | None = None):
    """reloc.Keypoints from a keypoints cloud. The image size and the detection scale do not travel:
    pass them (the landmarks of the same header carry the image size). Raises MessageError for
    missing or mistyped fields and non-finite values, LimitError for more than max_rows keypoints;
    zero rows is a valid (textureless) image."""
    from ...core.reloc import Keypoints

    what = 'keypoints cloud'
    table = cloud_to_array(msg, KEYPOINT_FIELDS, what, max_rows=max_rows)
    for name in ('u', 'v', 'size', 'angle', 'response'):
        if not np.isfinite(table[name]).all():
            raise MessageError(f'{what}: field {name!r} contains NaN or inf')
    depth = table['depth'].astype(np.float32) if 'depth' in table.dtype.names else None  # metres, NaN = none
    if depth is not None:
        check_fields(msg, (('depth', PointField.FLOAT32, 1),), what)
        if np.any(np.isinf(depth) | (depth <= 0)):
            raise MessageError(f'{what}: field depth must be positive metres or NaN')
    return Keypoints(
        uv=np.stack([table['u'], table['v']], axis=1).astype(np.float32),
        size=table['size'].astype(np.float32),
        angle=table['angle'].astype(np.float32),
        response=table['response'].astype(np.float32),
        octave=table['octave'].astype(np.int32),
        descriptors=np.ascontiguousarray(table['descriptor'], np.uint8).reshape(len(table), 32),
        scale=float(scale),
        image_size=tuple(int(v) for v in image_size),
        depth=depth,
    )
