"""lln_ros.ros.msgs: every table and image encoding round-trips, every malformed message is refused
with a MessageError. Real sensor_msgs classes and rclpy's real CDR serialization, no mocks."""

from __future__ import annotations

import array

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message, serialize_message
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField

from lln_ros.core.landmarks import LandmarkSet, l2_normalize, select_landmarks
from lln_ros.core.retrieval import pair_regions
from lln_ros.errors import MessageError
from lln_ros.ros import msgs


def make_landmarks(d=16, rows=9, cols=12, n=20, image_size=(512, 384), seed=0) -> LandmarkSet:
    """A landmark set laid out exactly as the extractor lays one out."""
    rng = np.random.default_rng(seed)
    local = rng.standard_normal((rows * cols, d)).astype(np.float32)
    activation = rng.random((rows, cols)).astype(np.float32)
    flat = select_landmarks(activation, n)
    cells = np.stack([flat % cols, flat // cols], axis=1).astype(np.int32)
    cell_size = np.array([image_size[0] / cols, image_size[1] / rows], np.float32)
    return LandmarkSet(
        global_descriptor=l2_normalize(local.max(axis=0)).astype(np.float32),
        descriptors=l2_normalize(local[flat]).astype(np.float32),
        cells=cells,
        centers=((cells + 0.5) * cell_size).astype(np.float32),
        scores=activation.ravel()[flat],
        cell_size=cell_size,
        image_size=np.array(image_size, np.float32),
        grid=(rows, cols),
        activation=activation,
        descriptor_space='test/layer/16',
    ).validate()


def roundtrip(msg):
    """Through rclpy's real CDR serialization and back."""
    return deserialize_message(serialize_message(msg), type(msg))


def header(sec=12, nanosec=345, frame_id='camera'):
    h = msgs.make_header(sec * 1_000_000_000 + nanosec, frame_id)
    assert (h.stamp.sec, h.stamp.nanosec) == (sec, nanosec)
    return h


def field(msg, name):
    return next(f for f in msg.fields if f.name == name)


# ---------------------------------------------------------------- generic tables


def test_generic_cloud_roundtrip_all_datatypes_and_array_fields():
    dtype = [
        ('i8', 'i1'),
        ('u8', 'u1'),
        ('i16', '<i2'),
        ('u16', '<u2'),
        ('i32', '<i4'),
        ('u32', '<u4'),
        ('f32', '<f4'),
        ('f64', '<f8'),
        ('vec', '<f4', (5,)),
        ('ids', '<u2', (3,)),
    ]
    rng = np.random.default_rng(1)
    table = np.zeros(7, dtype)
    for name in table.dtype.names:
        table[name] = rng.integers(0, 100, table[name].shape)
    table['f32'] += 0.25
    cloud = msgs.array_to_cloud(table, header())
    assert (cloud.height, cloud.width, cloud.is_bigendian, cloud.is_dense) == (1, 7, False, True)
    assert cloud.point_step == table.dtype.itemsize and cloud.row_step == cloud.point_step * 7
    assert len(cloud.data) == cloud.row_step
    assert field(cloud, 'vec').count == 5 and field(cloud, 'vec').datatype == PointField.FLOAT32
    assert field(cloud, 'ids').datatype == PointField.UINT16 and field(cloud, 'ids').count == 3
    assert field(cloud, 'f64').datatype == PointField.FLOAT64
    for msg in (cloud, roundtrip(cloud)):
        back = msgs.cloud_to_array(msg, [('vec', PointField.FLOAT32, 5), ('i8', PointField.INT8, 1)])
        assert back.dtype.names == table.dtype.names
        for name in table.dtype.names:
            np.testing.assert_array_equal(back[name], table[name])
        assert back.flags.writeable
        back['u8'][0] = 99  # the result is writable and does not alias the message
    assert msgs.cloud_to_array(cloud)['u8'][0] == table['u8'][0]


def test_generic_cloud_big_endian_input_array_is_sent_little_endian():
    table = np.array([(1, 2.5), (70000, -1.0)], [('a', '>u4'), ('b', '>f4')])
    cloud = msgs.array_to_cloud(table)
    assert bytes(cloud.data[:4]) == (1).to_bytes(4, 'little')
    back = msgs.cloud_to_array(cloud)
    np.testing.assert_array_equal(back['a'], [1, 70000])
    np.testing.assert_array_equal(back['b'], [2.5, -1.0])


def test_generic_cloud_with_padded_rows_and_layout_gaps():
    table = np.zeros(3, {'names': ['x', 'y'], 'formats': ['<f4', '<u4'], 'offsets': [0, 8], 'itemsize': 16})
    table['x'], table['y'] = [1, 2, 3], [4, 5, 6]
    cloud = msgs.array_to_cloud(table)
    assert cloud.point_step == 16 and field(cloud, 'y').offset == 8
    # the same table as 3 rows of 1 point, each row padded to 20 bytes
    padded = PointCloud2(height=3, width=1, fields=cloud.fields, point_step=16, row_step=20)
    padded.data = array.array('B', b''.join(bytes(cloud.data[i * 16 : (i + 1) * 16]) + b'\xee' * 4 for i in range(3)))
    back = msgs.cloud_to_array(padded)
    np.testing.assert_array_equal(back['x'], [1, 2, 3])
    np.testing.assert_array_equal(back['y'], [4, 5, 6])


def test_generic_empty_table():
    cloud = msgs.array_to_cloud(np.zeros(0, [('a', '<f4')]))
    assert cloud.width == 0 and len(cloud.data) == 0
    assert len(msgs.cloud_to_array(roundtrip(cloud), [('a', PointField.FLOAT32, 1)])) == 0


def small_cloud():
    return msgs.array_to_cloud(np.array([(1.0, 2), (3.0, 4)], [('a', '<f4'), ('b', '<u4')]))


@pytest.mark.parametrize(
    'required, match',
    [
        ([('c', PointField.FLOAT32, 1)], "required field 'c' is missing"),
        ([('a', PointField.FLOAT64, 1)], "field 'a' is FLOAT32, expected FLOAT64"),
        ([('b', PointField.UINT32, 4)], "field 'b' has count 1, expected 4"),
    ],
)
def test_generic_cloud_refuses_wrong_fields(required, match):
    with pytest.raises(MessageError, match=match):
        msgs.cloud_to_array(small_cloud(), required)


def test_generic_cloud_refuses_inconsistent_sizes():
    cloud = small_cloud()
    cloud.data = cloud.data[:-1]
    with pytest.raises(MessageError, match='truncated'):
        msgs.cloud_to_array(cloud)
    cloud = small_cloud()
    cloud.data = cloud.data + array.array('B', b'\0' * 8)
    with pytest.raises(MessageError, match='more than'):
        msgs.cloud_to_array(cloud)
    cloud = small_cloud()
    cloud.width = 3  # claims 3 points, holds 2
    cloud.row_step = cloud.point_step * 3
    with pytest.raises(MessageError, match='truncated'):
        msgs.cloud_to_array(cloud)
    cloud = small_cloud()
    cloud.row_step = cloud.point_step  # row_step < point_step * width
    with pytest.raises(MessageError, match='row_step'):
        msgs.cloud_to_array(cloud)
    cloud = small_cloud()
    cloud.point_step = 6  # field b (offset 4, 4 bytes) does not fit
    with pytest.raises(MessageError, match='does not fit'):
        msgs.cloud_to_array(cloud)


def test_generic_cloud_refuses_big_endian_and_unknown_datatype():
    cloud = small_cloud()
    cloud.is_bigendian = True
    with pytest.raises(MessageError, match='big-endian'):
        msgs.cloud_to_array(cloud)
    cloud = small_cloud()
    cloud.fields[1].datatype = 42
    with pytest.raises(MessageError, match='unknown PointField datatype 42'):
        msgs.cloud_to_array(cloud)
    with pytest.raises(MessageError, match='PointCloud2'):
        msgs.cloud_to_array(Image())


def test_array_to_cloud_refuses_non_tables():
    with pytest.raises(MessageError, match='structured'):
        msgs.array_to_cloud(np.zeros(3, np.float32))
    with pytest.raises(MessageError, match='no PointField datatype'):
        msgs.array_to_cloud(np.zeros(3, [('s', 'U4')]))
    with pytest.raises(MessageError, match='1-D'):
        msgs.array_to_cloud(np.zeros(3, [('m', '<f4', (2, 2))]))


# ---------------------------------------------------------------- landmarks


def assert_same_landmarks(a: LandmarkSet, b: LandmarkSet):
    np.testing.assert_array_equal(b.global_descriptor, a.global_descriptor)
    np.testing.assert_array_equal(b.descriptors, a.descriptors)
    np.testing.assert_array_equal(b.cells, a.cells)
    np.testing.assert_array_equal(b.centers, a.centers)
    np.testing.assert_array_equal(b.scores, a.scores)
    np.testing.assert_array_equal(b.cell_size, a.cell_size)
    np.testing.assert_array_equal(b.image_size, a.image_size)
    assert b.grid == a.grid
    assert b.cells.dtype == np.int32 and b.descriptors.dtype == np.float32


@pytest.mark.parametrize(
    'kwargs',
    [
        {},  # rtabmap frames: 512x384, 12x9 grid
        {'image_size': (64, 32), 'rows': 9, 'cols': 18, 'n': 50},  # Nordland: upsampled, fractional cells
        {'image_size': (960, 540), 'rows': 9, 'cols': 16, 'n': 144, 'd': 320},  # all cells, bigger D
        {'image_size': (641, 479), 'rows': 9, 'cols': 13, 'n': 1, 'd': 1},  # odd sizes, D = 1
    ],
)
def test_landmarks_roundtrip(kwargs):
    lset = make_landmarks(**kwargs)
    cloud = msgs.landmarks_to_cloud(lset, header())
    d = lset.dim
    assert cloud.width == len(lset) + 1 and cloud.height == 1
    assert field(cloud, 'descriptor').count == d and field(cloud, 'descriptor').datatype == PointField.FLOAT32
    table = msgs.cloud_to_array(cloud)
    w, h = lset.image_size
    np.testing.assert_allclose([table['u'][0], table['v'][0], table['w'][0], table['h'][0]], [w / 2, h / 2, w, h])
    np.testing.assert_allclose(table['score'][0], lset.activation.sum(), rtol=1e-6)
    assert (np.diff(table['score'][1:]) <= 0).all()  # landmarks by descending score
    for msg in (cloud, roundtrip(cloud)):
        back = msgs.cloud_to_landmarks(msg, expected_dim=d, descriptor_space=lset.descriptor_space)
        assert_same_landmarks(lset, back)
        assert back.descriptor_space == lset.descriptor_space
        assert back.activation is None
        assert back.meta['total_activation'] == pytest.approx(float(lset.activation.sum()), rel=1e-6)
    # a second hop (matcher republishing) keeps the total activation
    again = msgs.cloud_to_landmarks(msgs.landmarks_to_cloud(back))
    assert again.meta['total_activation'] == back.meta['total_activation']
    # the stamp is the caller's; the frame says it is a table, whatever frame the caller gave
    assert roundtrip(cloud).header.stamp.nanosec == 345 and roundtrip(cloud).header.frame_id == msgs.TABLE_FRAME


def test_landmarks_roundtrip_feeds_the_matcher():
    from lln_ros.core.similarity import match_pair

    a, b = make_landmarks(seed=1), make_landmarks(seed=2)
    a2, b2 = (msgs.cloud_to_landmarks(roundtrip(msgs.landmarks_to_cloud(s))) for s in (a, b))
    want, got = match_pair(a, b), match_pair(a2, b2)
    np.testing.assert_array_equal(got.scores, want.scores)
    np.testing.assert_array_equal(got.offsets, want.offsets)


def test_landmarks_wrong_dim():
    cloud = msgs.landmarks_to_cloud(make_landmarks(d=16))
    with pytest.raises(MessageError, match='D=16, expected D=32'):
        msgs.cloud_to_landmarks(cloud, expected_dim=32)


def test_landmarks_nan_descriptor():
    table = msgs.cloud_to_array(msgs.landmarks_to_cloud(make_landmarks()))
    table['descriptor'][3, 5] = np.nan
    with pytest.raises(MessageError, match='descriptors contain NaN or inf'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(table))
    table['descriptor'][3, 5] = 0
    table['u'][2] = np.inf
    with pytest.raises(MessageError, match="'u' contain NaN or inf"):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(table))


def test_landmarks_missing_field_and_wrong_datatype():
    table = msgs.cloud_to_array(msgs.landmarks_to_cloud(make_landmarks()))
    no_score = table[[n for n in table.dtype.names if n != 'score']]
    with pytest.raises(MessageError, match="required field 'score' is missing"):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(no_score))
    as_f64 = table.astype(
        [(n, '<f8', table.dtype[n].shape) if n == 'descriptor' else (n, table.dtype[n]) for n in table.dtype.names]
    )
    with pytest.raises(MessageError, match="'descriptor' is FLOAT64, expected FLOAT32"):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(as_f64))


def test_landmarks_zero_rows_and_no_landmarks():
    table = msgs.cloud_to_array(msgs.landmarks_to_cloud(make_landmarks()))
    with pytest.raises(MessageError, match='no rows'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(table[:0]))
    with pytest.raises(MessageError, match='only the whole-image row'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(table[:1]))


def test_landmarks_cells_outside_grid_and_bad_sizes():
    table = msgs.cloud_to_array(msgs.landmarks_to_cloud(make_landmarks()))
    bad = table.copy()
    bad['u'][4] = 600.0  # image is 512 wide
    with pytest.raises(MessageError, match='outside the 12x9 grid'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(bad))
    bad = table.copy()
    bad['v'][4] = -3.0
    with pytest.raises(MessageError, match='outside'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(bad))
    bad = table.copy()
    bad['w'][2] = 10.0
    with pytest.raises(MessageError, match='disagree on the grid cell size'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(bad))
    bad = table.copy()
    bad['h'][1:] = 0.0
    with pytest.raises(MessageError, match='positive'):
        msgs.cloud_to_landmarks(msgs.array_to_cloud(bad))


def test_landmarks_truncated():
    cloud = msgs.landmarks_to_cloud(make_landmarks())
    cloud.data = cloud.data[: len(cloud.data) - 7]
    with pytest.raises(MessageError, match='truncated'):
        msgs.cloud_to_landmarks(cloud)


def test_landmarks_without_activation_map():
    lset = make_landmarks()
    lset.activation = None
    back = msgs.cloud_to_landmarks(msgs.landmarks_to_cloud(lset))
    assert back.meta['total_activation'] == pytest.approx(float(lset.scores.sum()), rel=1e-6)


# ---------------------------------------------------------------- candidates and matches


def candidate_rows(extra=False):
    rows = [
        {'keyframe_id': 7, 'score': 3.5, 'holistic_score': 0.9, 'stamp_sec': 1700000000, 'stamp_nanosec': 999_999_999},
        {'keyframe_id': 4_000_000_000, 'score': 1.25, 'holistic_score': 0.5, 'stamp_sec': -2, 'stamp_nanosec': 0},
    ]
    if extra:
        rows[0].update(inliers=40.0, sequence_score=0.75)
        rows[1].update(inliers=3.0, sequence_score=0.25)
    return rows


@pytest.mark.parametrize('extra', [False, True])
def test_candidates_roundtrip(extra):
    rows = candidate_rows(extra)
    cloud = msgs.candidates_to_cloud(rows, header())
    types = {f.name: f.datatype for f in cloud.fields}
    assert types['keyframe_id'] == PointField.UINT32 and types['stamp_sec'] == PointField.INT32
    assert types['stamp_nanosec'] == PointField.UINT32 and types['score'] == PointField.FLOAT32
    if extra:
        assert types['inliers'] == types['sequence_score'] == PointField.FLOAT32
    for msg in (cloud, roundtrip(cloud)):
        back = msgs.cloud_to_candidates(msg)
        assert len(back) == 2
        for got, want in zip(back, rows):
            for key, value in want.items():
                assert got[key] == pytest.approx(value), key
    # a structured array works as input too, and keeps its extra fields
    again = msgs.cloud_to_candidates(msgs.candidates_to_cloud(msgs.cloud_to_candidates(cloud)))
    assert again.dtype.names == msgs.cloud_to_candidates(cloud).dtype.names


def test_candidates_empty_and_errors():
    empty = msgs.cloud_to_candidates(roundtrip(msgs.candidates_to_cloud([], header())))
    assert len(empty) == 0 and 'keyframe_id' in empty.dtype.names
    rows = candidate_rows()
    del rows[0]['stamp_nanosec'], rows[1]['stamp_nanosec']
    with pytest.raises(MessageError, match='stamp_nanosec'):
        msgs.candidates_to_cloud(rows)
    table = msgs.cloud_to_candidates(msgs.candidates_to_cloud(candidate_rows()))
    wrong = table.astype([(n, '<f4' if n == 'keyframe_id' else table.dtype[n]) for n in table.dtype.names])
    with pytest.raises(MessageError, match="'keyframe_id' is FLOAT32, expected UINT32"):
        msgs.cloud_to_candidates(msgs.array_to_cloud(wrong))
    table['score'][1] = np.nan
    with pytest.raises(MessageError, match='NaN'):
        msgs.cloud_to_candidates(msgs.array_to_cloud(table))


def test_landmarks_descriptors_renormalised_on_decode():
    lset = make_landmarks()
    lset.descriptors = lset.descriptors * 1e30  # finite, but inf once squared or stored as float16
    back = msgs.cloud_to_landmarks(msgs.landmarks_to_cloud(lset))
    np.testing.assert_allclose(np.linalg.norm(back.descriptors, axis=1), 1, rtol=1e-5)
    lset.descriptors[0] = 0
    with pytest.raises(MessageError, match='non-zero length'):
        msgs.cloud_to_landmarks(msgs.landmarks_to_cloud(lset))


def test_matches_roundtrip_and_match_rows():
    from lln_ros.core.similarity import match_pair

    a, b = make_landmarks(seed=1), make_landmarks(seed=1)
    b.descriptors = b.descriptors[::-1].copy()  # same landmarks, other order
    b.centers, b.cells, b.scores = b.centers[::-1].copy(), b.cells[::-1].copy(), b.scores[::-1].copy()
    pairs = match_pair(a, b).pairs(0)
    rows = msgs.match_rows(42, pair_regions(a, b, pairs))
    assert len(rows) == len(a)  # identical descriptors: every landmark is a mutual match
    np.testing.assert_array_equal(rows['query_u'], rows['map_u'])
    np.testing.assert_array_equal(rows['query_v'], rows['map_v'])
    cloud = msgs.matches_to_cloud(rows, header())
    assert {f.name: f.datatype for f in cloud.fields}['keyframe_id'] == PointField.UINT32
    for msg in (cloud, roundtrip(cloud)):
        back = msgs.cloud_to_matches(msg)
        for name, _, _ in msgs.MATCH_FIELDS:
            np.testing.assert_array_equal(back[name], rows[name])
    assert (back['keyframe_id'] == 42).all()
    np.testing.assert_allclose(back['cell_w'], 512 / 12)
    dict_rows = [{name: r[name].item() for name, _, _ in msgs.MATCH_FIELDS} for r in rows[:3]]
    np.testing.assert_array_equal(msgs.cloud_to_matches(msgs.matches_to_cloud(dict_rows))['map_u'], rows['map_u'][:3])
    assert len(msgs.cloud_to_matches(msgs.matches_to_cloud(msgs.match_rows(1, pair_regions(a, b, {}))))) == 0


def test_matches_errors():
    rows = msgs.match_rows(
        1,
        pair_regions(
            make_landmarks(),
            make_landmarks(),
            {'query_index': [0, 1], 'map_index': [1, 0], 'similarity': [0.9, 0.8], 'weight': [1.0, 0.5]},
        ),
    )
    table = msgs.cloud_to_matches(msgs.matches_to_cloud(rows))
    with pytest.raises(MessageError, match="'weight' is missing"):
        msgs.cloud_to_matches(msgs.array_to_cloud(table[[n for n in table.dtype.names if n != 'weight']]))
    cloud = msgs.matches_to_cloud(rows)
    cloud.data = cloud.data[:-4]
    with pytest.raises(MessageError, match='truncated'):
        msgs.cloud_to_matches(cloud)


# ---------------------------------------------------------------- images


@pytest.mark.parametrize(
    'encoding, channels, order',
    [('rgb8', 3, 'rgb'), ('bgr8', 3, 'bgr'), ('mono8', 1, 'rgb'), ('rgba8', 4, 'rgb'), ('bgra8', 4, 'bgr')],
)
def test_image_roundtrip(encoding, channels, order):
    rng = np.random.default_rng(4)
    shape = (37, 53) if channels == 1 else (37, 53, channels)
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    msg = msgs.array_to_image(image, encoding, header())
    assert (msg.height, msg.width, msg.step, msg.encoding) == (37, 53, 53 * channels, encoding)
    for m in (msg, roundtrip(msg)):
        back, got_order = msgs.image_to_array(m)
        assert got_order == order and back.dtype == np.uint8
        np.testing.assert_array_equal(back, image)
    assert roundtrip(msg).header.frame_id == 'camera'


@pytest.mark.parametrize('encoding, channels', [('rgb8', 3), ('mono8', 1), ('bgra8', 4)])
def test_image_padded_step(encoding, channels):
    rng = np.random.default_rng(5)
    h, w, pad = 11, 13, 7
    shape = (h, w) if channels == 1 else (h, w, channels)
    image = rng.integers(0, 256, shape, dtype=np.uint8)
    rows = image.reshape(h, w * channels)
    padded = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1)
    msg = Image(height=h, width=w, encoding=encoding, step=w * channels + pad)
    msg.data = array.array('B', padded.tobytes())
    for m in (msg, roundtrip(msg)):
        back, _ = msgs.image_to_array(m)
        np.testing.assert_array_equal(back, image)
        assert back.flags.c_contiguous


def test_image_errors():
    good = msgs.array_to_image(np.zeros((4, 5, 3), np.uint8), 'rgb8')
    msg = roundtrip(good)
    msg.encoding = '16UC1'
    with pytest.raises(MessageError, match="unsupported encoding '16UC1'"):
        msgs.image_to_array(msg)
    msg = roundtrip(good)
    msg.data = msg.data[:-1]
    with pytest.raises(MessageError, match='truncated'):
        msgs.image_to_array(msg)
    msg = roundtrip(good)
    msg.height = 0
    with pytest.raises(MessageError, match='empty image'):
        msgs.image_to_array(msg)
    msg = roundtrip(good)
    msg.step = 14  # < 5 * 3
    with pytest.raises(MessageError, match='step 14 is smaller'):
        msgs.image_to_array(msg)
    with pytest.raises(MessageError, match='unsupported encoding'):
        msgs.array_to_image(np.zeros((4, 5, 3), np.uint8), 'yuv422')
    with pytest.raises(MessageError, match='rgba8 needs a uint8 array'):
        msgs.array_to_image(np.zeros((4, 5, 3), np.uint8), 'rgba8')
    with pytest.raises(MessageError, match='uint8'):
        msgs.array_to_image(np.zeros((4, 5, 3), np.float32), 'rgb8')


@pytest.mark.parametrize('fmt', ['jpeg', 'png'])
def test_compressed_roundtrip(fmt):
    # smooth content so jpeg stays close
    yy, xx = np.mgrid[0:48, 0:64]
    rgb = np.stack([xx * 4, yy * 5, (xx + yy) * 2], axis=2).astype(np.uint8)
    msg = msgs.array_to_compressed(rgb, header(), fmt=fmt, channel_order='rgb')
    assert msg.format == fmt
    for m in (msg, roundtrip(msg)):
        bgr, order = msgs.compressed_to_array(m)
        assert order == 'bgr' and bgr.shape == (48, 64, 3)
        if fmt == 'png':
            np.testing.assert_array_equal(bgr[:, :, ::-1], rgb)
        else:
            assert np.abs(bgr[:, :, ::-1].astype(int) - rgb).mean() < 3
    # the format string from image_transport ('rgb8; jpeg compressed bgr8') works too
    ok, buf = cv2.imencode('.jpg', rgb[:, :, ::-1])
    m = CompressedImage(format='rgb8; jpeg compressed bgr8')
    m.data = array.array('B', buf.tobytes())
    assert msgs.message_to_array(m)[0].shape == (48, 64, 3)


def test_compressed_errors():
    m = CompressedImage(format='jpeg')
    with pytest.raises(MessageError, match='no data'):
        msgs.compressed_to_array(m)
    m.data = array.array('B', b'not an image at all')
    with pytest.raises(MessageError, match='cannot decode'):
        msgs.compressed_to_array(m)
    good = msgs.array_to_compressed(np.zeros((16, 16, 3), np.uint8))
    good.data = good.data[: len(good.data) // 3]
    with pytest.raises(MessageError, match='cannot decode'):
        msgs.compressed_to_array(good)
    m = CompressedImage(format='16UC1; compressedDepth')
    m.data = array.array('B', b'\0' * 20)
    with pytest.raises(MessageError, match='depth'):
        msgs.compressed_to_array(m)
