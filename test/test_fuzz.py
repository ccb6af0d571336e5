"""Fuzzing the codecs (lln_ros.ros.msgs) and the matcher's inputs (lln_ros.core.localizer) with Hypothesis.

Property: whatever a message holds, decoding ends in a result or a MessageError (LimitError for
sizes above the limits), never another exception, and never an allocation sized by a declared
number; a decoded landmark set given to the Localizer is answered, refused or failed, with the
counter sums kept. Seeded and bounded: derandomize=True (the same examples on every run), a small
max_examples per property, no per-example deadline (CI machines are loaded).
"""

import array
import json
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from sensor_msgs.msg import CompressedImage, Image, PointCloud2, PointField
from test_localizer import ask, invariants, keyframe
from test_mapstore import MODEL, SPACE, make_set

from lln_ros.core.limits import LimitError, default_conf, validate_model
from lln_ros.core.localizer import Localizer
from lln_ros.errors import MessageError, ModelError
from lln_ros.mapstore import open_for_matcher as open_map
from lln_ros.ros import msgs

FUZZ = settings(
    derandomize=True,
    max_examples=150,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.function_scoped_fixture],
)
SMALL = settings(FUZZ, max_examples=60)
LIMITS = {**default_conf, 'max_landmarks': 64, 'max_descriptor_dim': 512}
U32 = st.integers(0, 2**32 - 1)
DATATYPES = st.sampled_from(list(range(0, 10)))


@st.composite
def fields(draw):
    names = draw(st.lists(st.sampled_from(['u', 'v', 'w', 'h', 'score', 'descriptor', 'x', '']), max_size=7))
    return [
        PointField(
            name=n, offset=draw(st.integers(0, 64) | U32), datatype=draw(DATATYPES), count=draw(st.integers(0, 8) | U32)
        )
        for n in names
    ]


@st.composite
def raw_clouds(draw):
    """PointCloud2 with every header number and the data chosen freely (data stays small)."""
    msg = PointCloud2()
    msg.width, msg.height = draw(st.integers(0, 8) | U32), draw(st.integers(0, 3) | U32)
    msg.point_step, msg.row_step = draw(st.integers(0, 64) | U32), draw(st.integers(0, 256) | U32)
    msg.fields = draw(fields())
    msg.is_bigendian = draw(st.booleans())
    msg.data = array.array('B', draw(st.binary(max_size=512)))
    return msg


def table_cloud(draw, dim: int, n: int) -> PointCloud2:
    """A well-formed landmarks cloud with hostile values: sizes, centres and descriptors drawn freely."""
    floats = st.floats(width=32, allow_nan=True, allow_infinity=True) | st.floats(-1e3, 1e3, width=32)
    table = np.zeros(n, [(k, '<f4') for k in ('u', 'v', 'w', 'h', 'score')] + [('descriptor', '<f4', (dim,))])
    image = draw(
        st.sampled_from([(384, 288), (32768, 288), (1e9, 1e9), (1e-3, 1e-3), (64, 32)]) | st.tuples(floats, floats)
    )
    cell = draw(st.sampled_from([(32, 32), (1e-3, 1e-3), (32, 1e-6), (1e6, 1e6)]) | st.tuples(floats, floats))
    table['w'][0], table['h'][0] = image
    table['u'][0], table['v'][0] = image[0] / 2, image[1] / 2
    table['w'][1:], table['h'][1:] = cell
    rng = np.random.default_rng(draw(st.integers(0, 1000)))
    if draw(st.booleans()):  # centres inside the declared grid, so the sizes reach the limits checks
        with np.errstate(all='ignore'):
            cols, rows = (np.nan_to_num(np.float64(a) / np.float64(c), posinf=1e12) for a, c in zip(image, cell))
        for name, size, count in (('u', cell[0], cols), ('v', cell[1], rows)):
            table[name][1:] = (rng.integers(0, max(1, min(int(max(count, 1)), 2**40)), n - 1) + 0.5) * np.float64(size)
    else:
        centres = draw(st.lists(st.tuples(floats, floats), min_size=n - 1, max_size=n - 1))
        for i, (u, v) in enumerate(centres, start=1):
            table['u'][i], table['v'][i] = u, v
    table['descriptor'] = rng.standard_normal((n, dim)).astype(np.float32) * draw(st.sampled_from([1.0, 0.0, 1e30]))
    table['score'] = rng.random(n)
    return msgs.array_to_cloud(table)


@st.composite
def landmark_clouds(draw):
    return table_cloud(draw, draw(st.sampled_from([320, 8, 600])), draw(st.integers(1, 80)))


def only_message_errors(fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except MessageError:
        return None


@FUZZ
@given(raw_clouds())
def test_cloud_to_array_any_header(msg):
    out = only_message_errors(msgs.cloud_to_array, msg, max_rows=100)
    if out is not None:
        assert len(out) == int(msg.width) * int(msg.height) <= 100


@FUZZ
@given(raw_clouds())
def test_cloud_to_landmarks_and_keypoints_any_header(msg):
    only_message_errors(msgs.cloud_to_landmarks, msg, limits=LIMITS)
    only_message_errors(msgs.cloud_to_keypoints, msg, (640, 480), 1.0, max_rows=1000)
    only_message_errors(msgs.cloud_to_candidates, msg)
    only_message_errors(msgs.cloud_to_matches, msg)


@FUZZ
@given(landmark_clouds())
def test_cloud_to_landmarks_hostile_values(msg):
    lset = only_message_errors(msgs.cloud_to_landmarks, msg, limits=LIMITS)
    if lset is not None:
        assert len(lset) <= LIMITS['max_landmarks'] and lset.dim <= LIMITS['max_descriptor_dim']
        assert np.isfinite(lset.descriptors).all() and lset.validate() is lset


@st.composite
def images(draw):
    msg = Image()
    msg.encoding = draw(st.sampled_from(['rgb8', 'bgr8', 'mono8', 'rgba8', 'bgra8', '16UC1', '', 'x' * 40]))
    msg.width, msg.height = draw(st.integers(0, 64) | U32), draw(st.integers(0, 64) | U32)
    msg.step = draw(st.integers(0, 256) | U32)
    msg.data = array.array('B', draw(st.binary(max_size=4096)))
    return msg


@FUZZ
@given(images())
def test_image_to_array_any_header(msg):
    out = only_message_errors(msgs.image_to_array, msg, max_pixels=4096)
    if out is not None:
        assert out[0].shape[:2] == (msg.height, msg.width)


def png(width: int, height: int, body: bytes = b'') -> bytes:
    """A PNG whose IHDR says width x height (8-bit RGB) followed by `body` as its IDAT."""

    def chunk(kind, data):
        return struct.pack('>I', len(data)) + kind + data + struct.pack('>I', zlib.crc32(kind + data))

    return (
        b'\x89PNG\r\n\x1a\n'
        + chunk(b'IHDR', struct.pack('>IIBBBBB', width, height, 8, 2, 0, 0, 0))
        + chunk(b'IDAT', body)
        + chunk(b'IEND', b'')
    )


def jpeg_header(width: int, height: int) -> bytes:
    """SOI, an APP0 segment, then a baseline frame header (SOF0) of width x height."""
    app0 = b'\xff\xe0' + struct.pack('>H', 16) + b'JFIF\x00\x01\x01\x00\x00\x01\x00\x01\x00\x00'
    sof = b'\xff\xc0' + struct.pack('>HBHHB', 17, 8, height, width, 3) + bytes(9)
    return b'\xff\xd8' + app0 + sof


@st.composite
def compressed(draw):
    kind = draw(st.sampled_from(['png', 'jpeg', 'bytes', 'real']))
    w, h = draw(st.integers(0, 70000)), draw(st.integers(0, 70000))
    if kind == 'png':
        data = png(w, h, draw(st.binary(max_size=64)))
    elif kind == 'jpeg':
        data = jpeg_header(w, h) + draw(st.binary(max_size=64))
    elif kind == 'real':
        rng = np.random.default_rng(draw(st.integers(0, 100)))
        image = rng.integers(0, 256, (draw(st.integers(1, 40)), draw(st.integers(1, 40)), 3), np.uint8)
        data = bytes(msgs.array_to_compressed(image, fmt=draw(st.sampled_from(['jpeg', 'png']))).data)
        cut = draw(st.integers(0, len(data)))
        data = data[:cut] if draw(st.booleans()) else data
    else:
        data = draw(st.binary(max_size=256))
    return CompressedImage(
        format=draw(st.sampled_from(['jpeg', 'png', 'rgb8; compressedDepth', ''])), data=array.array('B', data)
    )


@FUZZ
@given(compressed())
def test_compressed_to_array_refuses_from_the_header(msg):
    """Headers declaring more than max_pixels are LimitError before decoding; nothing else escapes."""
    try:
        image, _ = msgs.compressed_to_array(msg, max_pixels=1_000_000)
    except LimitError as e:
        assert 'header' in str(e)
        return
    except MessageError:
        return
    assert image.shape[0] * image.shape[1] <= 1_000_000


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=20,
)
MODELISH = st.fixed_dictionaries(
    {
        'descriptor_space': st.sampled_from(['a/b/192', '', 'x', 'a/b/7']) | JSON,
        'descriptor_dim': st.sampled_from([192, 0, -1, 7, 2**70, 1e999, 1e30, 192.5, '192', True]) | JSON,
    },
    optional={'input_height': st.sampled_from([288, 100, 0, 2**40]) | JSON},
)


@FUZZ
@given(MODELISH | JSON)
def test_validate_model_any_json(model):
    try:
        out = validate_model(json.loads(json.dumps(model)))
    except ModelError:
        return
    except ValueError:  # not JSON-serialisable draws (NaN keys etc.) never reach the node
        return
    assert isinstance(out['descriptor_dim'], int) and 1 <= out['descriptor_dim'] <= default_conf['max_descriptor_dim']


@pytest.fixture(scope='module')
def served_map(tmp_path_factory):
    """A real SQLite map of 6 keyframes the Localizer fuzz examples query (read-only use)."""
    path = tmp_path_factory.mktemp('fuzzmap') / 'map.db'
    rng = np.random.default_rng(5)
    sets = [make_set(rng) for _ in range(6)]
    store, _ = open_map(path, descriptor_space=SPACE)
    loc = Localizer(store)
    for i, s in enumerate(sets):
        keyframe(loc, s, i)
    yield store, sets
    store.close()


@SMALL
@given(cloud=landmark_clouds(), prefilter_k=st.sampled_from([0, 3]))
def test_localizer_any_decoded_query(served_map, cloud, prefilter_k):
    """Any cloud the codec accepts, as a query: answered or a counted refusal; the node's next good
    query is answered with the right keyframe."""
    store, sets = served_map
    loc = Localizer(store, {'prefilter_k': prefilter_k, 'limits': LIMITS})
    loc.model_info(json.dumps(MODEL))
    args = loc.landmark_decoding('bad_query')
    if loc.query_fresh(1, 1):
        try:
            lset = msgs.cloud_to_landmarks(cloud, **args)
        except MessageError as e:
            loc.refuse('bad_query', e)
        else:
            if loc.query(lset, 1) is not None:
                loc.count('queries_answered')
    assert ask(loc, sets[3], 2).rows[0]['keyframe_id'] == 4
    counts = loc.counters.snapshot()
    assert 'queries_failed' not in counts, counts
    invariants(counts)


# --------------------------------------------------------------------------------------------
# issue 25: stamps, nesting depth, field counts and landmark counts at the limits


@FUZZ
@given(sec=st.integers(-(2**31), 2**31 - 1) | st.sampled_from([2**31 - 1, -(2**31), 0]), nsec=U32)
def test_any_stamp_is_refused_or_answered_exactly(sec, nsec):
    """Every builtin_interfaces/Time a sender can put in a header: refused with a MessageError, or
    carried to the answer's stamp_sec / stamp_nanosec bit for bit (never renormalised)."""
    header = msgs.make_header()
    header.stamp.sec, header.stamp.nanosec = sec, nsec
    try:
        ns = msgs.header_stamp_ns(header, 'query cloud')
    except MessageError:
        assert nsec >= 10**9
        return
    row = {'keyframe_id': 1, 'score': 1.0, 'holistic_score': 1.0}
    row['stamp_sec'], row['stamp_nanosec'] = divmod(ns, 10**9)
    table = msgs.cloud_to_candidates(msgs.candidates_to_cloud([row]))
    assert (int(table['stamp_sec'][0]), int(table['stamp_nanosec'][0])) == (sec, nsec)


@FUZZ
@given(depth=st.integers(0, 20) | st.integers(0, 20_000), kind=st.sampled_from(['list', 'dict', 'mixed']))
def test_model_info_any_nesting_depth(served_map, depth, kind):
    """A model_info with one value nested `depth` deep: recorded-or-refused, never an exception, and
    refused (bad_model_info) exactly when deeper than MODEL_JSON_MAX_DEPTH or larger than its bound."""
    from lln_ros.core.limits import MODEL_JSON_MAX_BYTES, MODEL_JSON_MAX_DEPTH

    opener, closer = {'list': ('[', ']'), 'dict': ('{"a": ', '}'), 'mixed': ('[{"a": ', '}]')}[kind]
    per = 2 if kind == 'mixed' else 1
    text = json.dumps(MODEL)[:-1] + ', "extra": ' + opener * depth + '1' + closer * depth + '}'
    store, _ = served_map
    loc = Localizer(store)
    loc.model_info(text)
    refused = loc.counters.snapshot().get('bad_model_info', 0) == 1
    assert refused == (1 + per * depth > MODEL_JSON_MAX_DEPTH or len(text) > MODEL_JSON_MAX_BYTES), (depth, kind)


@SMALL
@given(extra=st.integers(0, 120) | st.sampled_from([57, 58, 59, 40_000]))
def test_point_field_count_at_the_limit(extra):
    """A landmarks cloud with `extra` more valid PointFields: decoded up to max_point_fields, refused
    (LimitError) above it, whichever decoder gets it."""
    msg = msgs.landmarks_to_cloud(make_set(np.random.default_rng(0)))
    msg.fields = list(msg.fields) + [
        PointField(name=f'x{i}', offset=0, datatype=PointField.UINT8, count=1) for i in range(extra)
    ]
    over = len(msg.fields) > default_conf['max_point_fields']
    for decode in (msgs.cloud_to_landmarks, msgs.cloud_to_array, msgs.cloud_to_candidates):
        try:
            decode(msg)
        except LimitError:
            assert over
        except MessageError:
            assert not over and decode is msgs.cloud_to_candidates  # not a candidates table
        else:
            assert not over


def grid_set(rng, n: int, dim: int = 8, side: int = 64):
    from lln_ros.core.landmarks import LandmarkSet

    desc = rng.standard_normal((n, dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    flat = rng.choice(side * side, n, replace=False)
    cells = np.stack([flat % side, flat // side], axis=1).astype(np.int32)
    return LandmarkSet(
        global_descriptor=desc[0],
        descriptors=desc,
        cells=cells,
        centers=(cells * 32 + 16).astype(np.float32),
        scores=np.ones(n, np.float32),
        cell_size=np.array([32, 32], np.float32),
        image_size=np.array([side * 32, side * 32], np.float32),
        grid=(side, side),
    )


@settings(FUZZ, max_examples=10)
@given(
    counts=st.lists(st.sampled_from([1, 50, 1152, 4095, 4096]) | st.integers(1, 4096), min_size=1, max_size=5),
    n_q=st.sampled_from([1, 50, 4096]) | st.integers(1, 4096),
    seed=st.integers(0, 100),
)
def test_batched_match_at_the_landmark_limit(counts, n_q, seed):
    """Candidates of any landmark counts up to max_landmarks (4096) against a query of up to 4096:
    every chunk the match works on stays within MATCH_CHUNK_ELEMENTS (or is one candidate), and
    each score equals the candidate matched alone."""
    from lln_ros.core import similarity

    rng = np.random.default_rng(seed)
    sets, query = [grid_set(rng, n) for n in counts], grid_set(rng, n_q)
    seen, inner = [], similarity._match_chunk

    def recording(q, batch, *args):
        k, n_b, d = batch.descriptors.shape
        seen.append((k, n_b, d))
        return inner(q, batch, *args)

    similarity._match_chunk = recording
    try:
        result = similarity.match_sets(query, sets)
    finally:
        similarity._match_chunk = inner
    cap = similarity.MATCH_CHUNK_ELEMENTS
    assert all(k == 1 or k * n_b * d <= cap for k, n_b, d in seen), seen
    alone = [similarity.match_pair(query, s).scores[0] for s in sets]
    np.testing.assert_allclose(result.scores, alone, rtol=1e-4, atol=1e-4)
