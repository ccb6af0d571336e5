"""Typed tables as sensor_msgs/PointCloud2 (see the package docstring for the layout of each)."""

from __future__ import annotations

import array as _array
from collections.abc import Mapping, Sequence

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from ...core.landmarks import LandmarkSet
from ...core.limits import LimitError
from ...core.limits import default_conf as LIMITS
from ...errors import DescriptorError, MessageError
from .headers import TABLE_FRAME

__all__ = [
    'LANDMARK_FIELDS',
    'CANDIDATE_FIELDS',
    'KEYPOINT_FIELDS',
    'MATCH_FIELDS',
    'datatype_name',
    'dtype_to_fields',
    'array_to_cloud',
    'check_fields',
    'cloud_to_array',
    'landmarks_to_cloud',
    'cloud_to_landmarks',
    'candidates_to_cloud',
    'cloud_to_candidates',
    'matches_to_cloud',
    'cloud_to_matches',
    'match_rows',
]


# PointField datatype <-> little-endian numpy scalar type
_DATATYPES = {
    PointField.INT8: np.dtype('i1'),
    PointField.UINT8: np.dtype('u1'),
    PointField.INT16: np.dtype('<i2'),
    PointField.UINT16: np.dtype('<u2'),
    PointField.INT32: np.dtype('<i4'),
    PointField.UINT32: np.dtype('<u4'),
    PointField.FLOAT32: np.dtype('<f4'),
    PointField.FLOAT64: np.dtype('<f8'),
}
_DATATYPE_NAMES = {
    getattr(PointField, name): name
    for name in ('INT8', 'UINT8', 'INT16', 'UINT16', 'INT32', 'UINT32', 'FLOAT32', 'FLOAT64')
}
_KIND_SIZE_TO_DATATYPE = {(dt.kind, dt.itemsize): code for code, dt in _DATATYPES.items()}

LANDMARK_FIELDS = (
    ('u', PointField.FLOAT32, 1),
    ('v', PointField.FLOAT32, 1),
    ('w', PointField.FLOAT32, 1),
    ('h', PointField.FLOAT32, 1),
    ('score', PointField.FLOAT32, 1),
)  # + ('descriptor', FLOAT32, D)
CANDIDATE_FIELDS = (
    ('keyframe_id', PointField.UINT32, 1),
    ('score', PointField.FLOAT32, 1),
    ('holistic_score', PointField.FLOAT32, 1),
    ('stamp_sec', PointField.INT32, 1),
    ('stamp_nanosec', PointField.UINT32, 1),
)
KEYPOINT_FIELDS = (
    ('u', PointField.FLOAT32, 1),
    ('v', PointField.FLOAT32, 1),
    ('size', PointField.FLOAT32, 1),
    ('angle', PointField.FLOAT32, 1),
    ('response', PointField.FLOAT32, 1),
    ('octave', PointField.INT32, 1),
    ('descriptor', PointField.UINT8, 32),
)  # ORB: 256-bit binary descriptor
MATCH_FIELDS = (('keyframe_id', PointField.UINT32, 1),) + tuple(
    (name, PointField.FLOAT32, 1)
    for name in ('query_u', 'query_v', 'map_u', 'map_v', 'cell_w', 'cell_h', 'similarity', 'weight')
)


def datatype_name(datatype: int) -> str:
    return _DATATYPE_NAMES.get(datatype, f'unknown({datatype})')


# --------------------------------------------------------------------------------------------
# generic tables


def dtype_to_fields(dtype: np.dtype) -> list[PointField]:
    """PointFields describing a structured dtype (offsets as laid out in the dtype)."""
    if dtype.names is None:
        raise MessageError(f'a table must be a numpy structured array, got dtype {dtype}')
    fields = []
    for name in dtype.names:
        sub, offset = dtype.fields[name][:2]
        base, shape = sub.subdtype if sub.subdtype is not None else (sub, ())
        if len(shape) > 1:
            raise MessageError(f'field {name!r} has shape {shape}; only scalar or 1-D array fields fit a PointField')
        code = _KIND_SIZE_TO_DATATYPE.get((base.kind, base.itemsize))
        if code is None:
            raise MessageError(f'field {name!r} has dtype {base}, which no PointField datatype can hold')
        count = int(shape[0]) if shape else 1
        if count < 1:
            raise MessageError(f'field {name!r} is an empty array (count 0)')
        fields.append(PointField(name=name, offset=int(offset), datatype=code, count=count))
    return fields


def _little_endian(dtype: np.dtype) -> np.dtype:
    """The same layout with every field little-endian."""
    return np.dtype(
        {
            'names': list(dtype.names),
            'formats': [dtype.fields[n][0].newbyteorder('<') for n in dtype.names],
            'offsets': [dtype.fields[n][1] for n in dtype.names],
            'itemsize': dtype.itemsize,
        }
    )


def array_to_cloud(records: np.ndarray, header: Header | None = None) -> PointCloud2:
    """PointCloud2 (height 1, one point per record, little-endian, dense) from a structured array.

    Array fields (e.g. ('descriptor', '<f4', (D,))) become one PointField with count D.
    """
    records = np.asarray(records)
    if records.ndim != 1:
        raise MessageError(f'a table must be a 1-D structured array, got shape {records.shape}')
    fields = dtype_to_fields(records.dtype)
    le = np.ascontiguousarray(records.astype(_little_endian(records.dtype), copy=False))
    msg = PointCloud2()
    # the stamp is the caller's, the frame says 'a table' (headers.TABLE_FRAME)
    msg.header = Header(stamp=header.stamp if header is not None else Header().stamp, frame_id=TABLE_FRAME)
    msg.height = 1
    msg.width = int(len(le))
    msg.fields = fields
    msg.is_bigendian = False
    msg.point_step = int(le.dtype.itemsize)
    msg.row_step = msg.point_step * msg.width
    msg.data = _array.array('B', le.tobytes())
    msg.is_dense = True
    return msg


def _fields_to_dtype(msg: PointCloud2, what: str) -> np.dtype:
    """The records' dtype, linear in the field count (check_fields bounds it first; issue 25)."""
    names, formats, offsets, seen = [], [], [], set()
    for f in msg.fields:
        if f.datatype not in _DATATYPES:
            raise MessageError(f'{what}: field {f.name!r} has unknown PointField datatype {f.datatype}')
        if f.count < 1:
            raise MessageError(f'{what}: field {f.name!r} has count {f.count}; it must be at least 1')
        if f.name in seen:
            raise MessageError(f'{what}: field {f.name!r} appears twice')
        seen.add(f.name)
        base = _DATATYPES[f.datatype]
        size = base.itemsize * f.count
        if f.offset + size > msg.point_step:
            raise MessageError(
                f'{what}: field {f.name!r} (offset {f.offset}, {size} bytes) does not fit '
                f'in point_step {msg.point_step}'
            )
        names.append(f.name)
        formats.append(base if f.count == 1 else np.dtype((base, (f.count,))))
        offsets.append(f.offset)
    try:
        return np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': int(msg.point_step)})
    except (ValueError, TypeError) as exc:
        raise MessageError(f'{what}: fields cannot be laid out in point_step {msg.point_step}: {exc}') from exc


def check_fields(
    msg: PointCloud2, required: Sequence[tuple], what: str = 'cloud', max_fields: int = LIMITS['max_point_fields']
) -> None:
    """Raise MessageError unless every (name, datatype, count) in `required` is present as given.
    A count of None accepts any count. LimitError first for more than max_fields PointFields."""
    if len(msg.fields) > max_fields:
        raise LimitError(f'{what}: {len(msg.fields)} PointFields is more than max_point_fields {max_fields}')
    present = {f.name: f for f in msg.fields}
    for name, datatype, count in required:
        f = present.get(name)
        if f is None:
            raise MessageError(
                f'{what}: required field {name!r} is missing (fields present: {sorted(present) or "none"})'
            )
        if f.datatype != datatype:
            raise MessageError(
                f'{what}: field {name!r} is {datatype_name(f.datatype)}, expected {datatype_name(datatype)}'
            )
        if count is not None and f.count != count:
            raise MessageError(f'{what}: field {name!r} has count {f.count}, expected {count}')


def cloud_to_array(
    msg: PointCloud2,
    required: Sequence[tuple] = (),
    what: str = 'cloud',
    max_rows: int | None = None,
    max_fields: int = LIMITS['max_point_fields'],
) -> np.ndarray:
    """Structured array (width * height records, every field of the cloud) from a PointCloud2.

    Checks the required fields (see check_fields), refuses big-endian clouds, and checks that
    point_step, row_step, width * height and len(data) agree. max_rows: LimitError for a cloud of
    more rows, before anything is copied (max_fields: more PointFields). The result owns its memory."""
    if not isinstance(msg, PointCloud2):
        raise MessageError(f'{what}: expected a sensor_msgs/PointCloud2, got {type(msg).__name__}')
    if msg.is_bigendian:
        raise MessageError(f'{what}: big-endian clouds are not supported')
    width, height, point_step, row_step = int(msg.width), int(msg.height), int(msg.point_step), int(msg.row_step)
    n = width * height
    if max_rows is not None and n > max_rows:
        raise LimitError(f'{what}: {width} x {height} = {n} rows is more than the limit of {max_rows}')
    check_fields(msg, required, what, max_fields)
    data = msg.data
    nbytes = len(data)
    if n and point_step < 1:
        raise MessageError(f'{what}: point_step is {point_step} for {n} points')
    dtype = _fields_to_dtype(msg, what)
    if n == 0:
        if nbytes:
            raise MessageError(f'{what}: width x height is 0 but data holds {nbytes} bytes')
        return np.zeros(0, dtype)
    if row_step < point_step * width:
        raise MessageError(
            f'{what}: row_step {row_step} is smaller than point_step x width = '
            f'{point_step} x {width} = {point_step * width}'
        )
    expected = row_step * height
    if nbytes < expected:
        raise MessageError(
            f'{what}: data is truncated: {nbytes} bytes, expected row_step x height = '
            f'{row_step} x {height} = {expected}'
        )
    if nbytes > expected:
        raise MessageError(
            f'{what}: data holds {nbytes} bytes, more than row_step x height = {row_step} x {height} = {expected}'
        )
    raw = np.frombuffer(data, np.uint8)
    if row_step != point_step * width:  # padded rows: drop the padding
        raw = raw.reshape(height, row_step)[:, : point_step * width]
    return np.array(raw, np.uint8, copy=True).reshape(-1).view(dtype)


def _records(rows, fields: Sequence[tuple], what: str) -> np.ndarray:
    """Structured array with the standard `fields` first, then extras (FLOAT32), from either a
    structured array or a sequence of mappings (all with the same keys)."""
    base = [(name, _DATATYPES[dt]) for name, dt, _ in fields]
    std = {name for name, _ in base}
    if isinstance(rows, np.ndarray) and rows.dtype.names is not None:
        missing = [n for n in std if n not in rows.dtype.names]
        if missing:
            raise MessageError(f'{what}: rows lack field(s) {missing}')
        extras = [(n, rows.dtype.fields[n][0]) for n in rows.dtype.names if n not in std]
        out = np.zeros(len(rows), base + extras)
        for n in out.dtype.names:
            out[n] = rows[n]
        return out
    rows = list(rows)
    keys = set(rows[0]) if rows else set(std)
    for i, r in enumerate(rows):
        if not isinstance(r, Mapping):
            raise MessageError(f'{what}: row {i} is a {type(r).__name__}, expected a mapping')
        if set(r) != keys:
            raise MessageError(f'{what}: row {i} has keys {sorted(r)}, row 0 has {sorted(keys)}')
    missing = sorted(std - keys)
    if missing:
        raise MessageError(f'{what}: rows lack field(s) {missing}')
    extras = [(k, np.dtype('<f4')) for k in sorted(keys - std)]
    out = np.zeros(len(rows), base + extras)
    for n in out.dtype.names:
        values = [r[n] for r in rows]
        kind = out.dtype.fields[n][0]
        if kind.kind in 'iu' and values:  # numpy would raise OverflowError (or wrap): name the value
            info = np.iinfo(kind)
            bad = next((v for v in values if not info.min <= int(v) <= info.max), None)
            if bad is not None:
                raise MessageError(f'{what}: {n} {bad} does not fit {kind.name} [{info.min}, {info.max}]')
        out[n] = values
    return out


# --------------------------------------------------------------------------------------------
# landmarks


def landmarks_to_cloud(lset: LandmarkSet, header: Header | None = None) -> PointCloud2:
    """The extractor's output. Row 0: the whole image (global descriptor, u/v the image centre,
    w/h the image size, score the total LLN activation); rows 1..n: the landmarks in the set's
    order (descending score), u/v the region centre, w/h the grid cell size, in image pixels.

    The total activation is activation.sum(); without an activation map it is
    meta['total_activation'] when present, else the sum of the landmark scores."""
    d = lset.dim
    n = len(lset)
    table = np.zeros(
        n + 1, [('u', '<f4'), ('v', '<f4'), ('w', '<f4'), ('h', '<f4'), ('score', '<f4'), ('descriptor', '<f4', (d,))]
    )
    image_w, image_h = (float(x) for x in lset.image_size)
    if lset.activation is not None:
        total = float(np.sum(lset.activation))
    else:
        total = float(lset.meta.get('total_activation', np.sum(lset.scores)))
    table[0] = (image_w / 2, image_h / 2, image_w, image_h, total, lset.global_descriptor)
    if n:
        table['u'][1:] = lset.centers[:, 0]
        table['v'][1:] = lset.centers[:, 1]
        table['w'][1:] = lset.cell_size[0]
        table['h'][1:] = lset.cell_size[1]
        table['score'][1:] = lset.scores
        table['descriptor'][1:] = lset.descriptors
    return array_to_cloud(table, header)


def cloud_to_landmarks(
    msg: PointCloud2, expected_dim: int | None = None, descriptor_space: str = '', limits: Mapping | None = None
) -> LandmarkSet:
    """LandmarkSet from a landmarks cloud (see landmarks_to_cloud).

    Cells are rebuilt as col = floor(u / w), row = floor(v / h), the grid as
    (round(image_h / cell_h), round(image_w / cell_w)). The activation map does not travel:
    `activation` is None and meta['total_activation'] holds row 0's score. The descriptor space
    does not travel either: pass it (e.g. from a parameter) to keep maps from mixing models.
    Raises MessageError for missing/mistyped fields, a descriptor size other than expected_dim,
    zero rows, no landmark rows, NaN/inf values, inconsistent cell sizes or cells off the grid.
    limits (lln_ros.core.limits.default_conf keys): LimitError for more than max_landmarks landmark rows
    or a D above max_descriptor_dim, checked before the data is copied; the declared image and
    cell sizes are the caller's to check (limits.check_landmark_set) once the set is decoded.
    """
    what = 'landmarks cloud'
    if limits is not None and isinstance(msg, PointCloud2):
        rows = int(msg.width) * int(msg.height)
        if rows > limits['max_landmarks'] + 1:
            raise LimitError(f'{what}: {rows - 1} landmark rows is more than max_landmarks {limits["max_landmarks"]}')
    max_fields = (limits or LIMITS).get('max_point_fields', LIMITS['max_point_fields'])
    check_fields(msg, LANDMARK_FIELDS + (('descriptor', PointField.FLOAT32, None),), what, max_fields)
    dim = next(f.count for f in msg.fields if f.name == 'descriptor')
    if limits is not None and dim > limits['max_descriptor_dim']:
        raise LimitError(
            f'{what}: descriptors have D={dim}, more than max_descriptor_dim {limits["max_descriptor_dim"]}'
        )
    if expected_dim is not None and dim != int(expected_dim):
        raise MessageError(
            f'{what}: descriptors have D={dim}, expected D={int(expected_dim)} '
            '(extractor and matcher use different models?)'
        )
    table = cloud_to_array(msg, what=what, max_fields=max_fields)
    if len(table) == 0:
        raise MessageError(f'{what}: no rows (row 0, the whole image, is required)')
    if len(table) == 1:
        raise MessageError(f'{what}: only the whole-image row; at least one landmark row is required')
    for name in ('u', 'v', 'w', 'h', 'score', 'descriptor'):
        if not np.isfinite(table[name]).all():
            bad = 'descriptors' if name == 'descriptor' else f'field {name!r}'
            raise MessageError(f'{what}: {bad} contain NaN or inf')
    image_w, image_h = float(table['w'][0]), float(table['h'][0])
    lm = table[1:]
    cell_w, cell_h = float(lm['w'][0]), float(lm['h'][0])
    if min(image_w, image_h, cell_w, cell_h) <= 0:
        raise MessageError(f'{what}: sizes must be positive (image {image_w}x{image_h}, cell {cell_w}x{cell_h})')
    if not (np.allclose(lm['w'], cell_w, rtol=1e-5) and np.allclose(lm['h'], cell_h, rtol=1e-5)):
        raise MessageError(f'{what}: landmark rows disagree on the grid cell size')
    rows, cols = int(round(image_h / cell_h)), int(round(image_w / cell_w))
    cells = np.stack(
        [np.floor(lm['u'].astype(np.float64) / cell_w), np.floor(lm['v'].astype(np.float64) / cell_h)], axis=1
    )
    if (cells < 0).any() or (cells[:, 0] >= cols).any() or (cells[:, 1] >= rows).any():
        raise MessageError(
            f'{what}: landmark centres fall outside the {cols}x{rows} grid of a {image_w:g}x{image_h:g} image'
        )
    # descriptors not of unit length (another sender, or huge finite values that would become inf
    # in the float16 map) are normalised in float64; unit ones pass through bit for bit
    desc = np.array(table['descriptor'], np.float32).reshape(len(table), dim)
    norms = np.linalg.norm(desc.astype(np.float64), axis=1, keepdims=True)
    if not (np.isfinite(norms).all() and (norms > 0).all()):
        raise MessageError(f'{what}: descriptors must have a finite, non-zero length')
    off = np.abs(norms[:, 0] - 1) > 1e-3
    desc[off] = (desc[off].astype(np.float64) / norms[off]).astype(np.float32)
    lset = LandmarkSet(
        global_descriptor=desc[0],
        descriptors=desc[1:],
        cells=cells.astype(np.int32),
        centers=np.stack([lm['u'], lm['v']], axis=1).astype(np.float32),
        scores=np.array(lm['score'], np.float32),
        cell_size=np.array([cell_w, cell_h], np.float32),
        image_size=np.array([image_w, image_h], np.float32),
        grid=(rows, cols),
        activation=None,
        descriptor_space=descriptor_space,
        meta={'total_activation': float(table['score'][0])},
    )
    try:
        return lset.validate()
    except DescriptorError as exc:
        raise MessageError(f'{what}: {exc}') from exc


# --------------------------------------------------------------------------------------------
# candidates and matches


def candidates_to_cloud(rows, header: Header | None = None, extra_fields: Sequence[str] = ()) -> PointCloud2:
    """The matcher's candidates, in the given order (best first). `rows`: a sequence of mappings
    with keyframe_id, score, holistic_score, stamp_sec, stamp_nanosec and any extra keys (sent as
    FLOAT32 fields, e.g. inliers, sequence_score), or a structured array with those fields.
    extra_fields: FLOAT32 fields a zero-row answer carries too, so its layout matches the others'."""
    if not isinstance(rows, np.ndarray) and not len(rows) and extra_fields:
        rows = np.zeros(
            0,
            [(name, _DATATYPES[dt]) for name, dt, _ in CANDIDATE_FIELDS]
            + [(name, np.dtype('<f4')) for name in sorted(extra_fields)],  # in name order, as _records lays out rows
        )
    return array_to_cloud(_records(rows, CANDIDATE_FIELDS, 'candidates'), header)


def cloud_to_candidates(msg: PointCloud2) -> np.ndarray:
    """Structured array of candidates (the standard fields plus any extra fields of the cloud)."""
    what = 'candidates cloud'
    table = cloud_to_array(msg, CANDIDATE_FIELDS, what)
    for name in ('score', 'holistic_score'):  # extra fields may use NaN for "not computed"
        if not np.isfinite(table[name]).all():
            raise MessageError(f'{what}: field {name!r} contains NaN or inf')
    return table


def matches_to_cloud(rows, header: Header | None = None) -> PointCloud2:
    """Matched region pairs (of the best candidate). `rows`: mappings or a structured array with
    keyframe_id, query_u, query_v, map_u, map_v, cell_w, cell_h, similarity, weight."""
    return array_to_cloud(_records(rows, MATCH_FIELDS, 'matches'), header)


def cloud_to_matches(msg: PointCloud2) -> np.ndarray:
    """Structured array of matched region pairs."""
    what = 'matches cloud'
    table = cloud_to_array(msg, MATCH_FIELDS, what)
    for name, _, _ in MATCH_FIELDS[1:]:
        if not np.isfinite(table[name]).all():
            raise MessageError(f'{what}: field {name!r} contains NaN or inf')
    return table


def match_rows(keyframe_id: int, regions: Mapping) -> np.ndarray:
    """Rows for matches_to_cloud from matched regions in pixels (retrieval.pair_regions, or
    MapCandidate.pairs): query_u, query_v, map_u, map_v, cell_w, cell_h, similarity, weight."""
    m = len(regions.get('similarity', ()))
    out = np.zeros(m, [(name, _DATATYPES[dt]) for name, dt, _ in MATCH_FIELDS])
    out['keyframe_id'] = keyframe_id
    for name, _, _ in MATCH_FIELDS[1:]:
        out[name] = np.asarray(regions[name], np.float32) if m else out[name]
    return out
