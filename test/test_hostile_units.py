"""Issue 25 at the codec, limit, store and Localizer level (no DDS; the node-level tests are in
test_hostile_round2.py): every class of the second hostile round, on the real parts."""

from __future__ import annotations

import json
import os
import sqlite3
import struct
import time
import tracemalloc

import cv2
import numpy as np
import pytest
from sensor_msgs.msg import CompressedImage, PointCloud2, PointField
from test_localizer import Log, ask, invariants, keyframe, stamp
from test_mapstore import MODEL, SPACE, make_set

from lln_ros.core import similarity
from lln_ros.core.counters import Counters
from lln_ros.core.landmarks import LandmarkSet, stack_landmarks
from lln_ros.core.limits import (
    MODEL_JSON_MAX_DEPTH,
    LimitError,
    json_shape_problem,
    parse_model_json,
    stamp_problem,
)
from lln_ros.core.localizer import KEYPOINT_ROW_BYTES, Localizer
from lln_ros.core.pending import Pending
from lln_ros.errors import MapError, MessageError, ModelError
from lln_ros.mapstore import MapStore
from lln_ros.mapstore import open_for_matcher as open_map
from lln_ros.ros import msgs

# ---------------------------------------------------------------------------------------- 1. stamps


@pytest.mark.parametrize(
    'sec, nsec, ok',
    [
        (2**31 - 1, 999_999_999, True),
        (0, 0, True),
        (-(2**31), 0, True),
        (2**31 - 1, 2**32 - 1, False),  # the stamp: renormalised, sec no longer fits int32
        (5, 1_000_000_000, False),
        (2**31, 0, False),
        (0, -1, False),
    ],
)
def test_stamp_checked_against_every_type_it_is_written_to(sec, nsec, ok):
    assert (stamp_problem(sec, nsec) == '') is ok
    stamp_msg = msgs.make_header().stamp
    if -(2**31) <= sec < 2**31 and 0 <= nsec < 2**32:  # what a builtin_interfaces/Time can hold
        stamp_msg.sec, stamp_msg.nanosec = sec, nsec
        if ok:
            assert divmod(msgs.header_stamp_ns(stamp_msg), 10**9) == (sec, nsec)
        else:
            with pytest.raises(MessageError, match='refused, not renormalised|int32'):
                msgs.header_stamp_ns(stamp_msg, 'query cloud')


def test_candidates_encoder_names_a_value_out_of_range_instead_of_overflowing():
    row = {'keyframe_id': 1, 'score': 0.5, 'holistic_score': 0.5, 'stamp_sec': 2**31 + 3, 'stamp_nanosec': 0}
    with pytest.raises(MessageError, match='stamp_sec 2147483651 does not fit int32'):
        msgs.candidates_to_cloud([row])
    row['stamp_sec'] = 2**31 - 1
    table = msgs.cloud_to_candidates(msgs.candidates_to_cloud([row]))
    assert int(table['stamp_sec'][0]) == 2**31 - 1


def test_store_refuses_and_quarantines_stamps_that_do_not_fit(tmp_path):
    """add() refuses a stamp the answers could not carry; a keyframe an older version stored with one
    (written here with SQL, as it was) is quarantined at open: queries are answered from the rest."""
    rng = np.random.default_rng(1)
    sets = [make_set(rng) for _ in range(4)]
    path = tmp_path / 'map.db'
    with MapStore(path, model=MODEL) as store:
        with pytest.raises(ValueError, match='int32'):
            store.add(sets[0], (2**31, 0))
        for i, s in enumerate(sets):
            store.add(s, (100 + i, 7))
    with sqlite3.connect(path) as con:
        con.execute('UPDATE keyframes SET stamp_sec = ? WHERE id = 2', (2**31 + 3,))
    store, quarantined = open_map(path, descriptor_space=SPACE)
    with store:
        assert list(quarantined) == [2] and 'int32' in quarantined[2]
        loc = Localizer(store, {'prefilter_k': 0})
        answer = ask(loc, sets[1], 1)  # the place of the damaged keyframe
        assert answer is not None and 2 not in [r['keyframe_id'] for r in answer.rows]
        assert [r['stamp_sec'] for r in answer.rows] == [100 + r['keyframe_id'] - 1 for r in answer.rows]
        msgs.candidates_to_cloud(answer.rows)  # encodable
        # any backend: a stored stamp out of range is left out of an answer and counted
        assert not loc._stamp_ok(9, (2**31 - 1 + 4, 0)) and loc.counters.snapshot()['bad_stored_stamp'] == 1
        assert not loc._stamp_ok(2**32, (1, 0)) and loc._stamp_ok(2**32 - 1, (1, 0))  # keyframe_id is UINT32
        with pytest.raises(ValueError, match='UINT32'):
            store.add_many([sets[0]], [(1, 0)], ids=[2**32])


# ------------------------------------------------------------------------------- 2. batched match


def big_set(rng, n: int, dim: int = 192, side: int = 64) -> LandmarkSet:
    """n landmarks (up to side x side, one per cell) on a side x side grid of 32 px cells."""
    desc = rng.standard_normal((n, dim)).astype(np.float32)
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)
    flat = rng.choice(side * side, n, replace=False)
    cells = np.stack([flat % side, flat // side], axis=1).astype(np.int32)
    glob = desc.mean(0) / np.linalg.norm(desc.mean(0))
    return LandmarkSet(
        global_descriptor=glob.astype(np.float32),
        descriptors=desc,
        cells=cells,
        centers=(cells * 32 + 16).astype(np.float32),
        scores=np.ones(n, np.float32),
        cell_size=np.array([32, 32], np.float32),
        image_size=np.array([side * 32, side * 32], np.float32),
        grid=(side, side),
        descriptor_space=SPACE,
    ).validate()


def test_match_sets_agrees_with_the_padded_batch_in_any_chunking(monkeypatch):
    rng = np.random.default_rng(2)
    sets = [big_set(rng, int(n), dim=16, side=16) for n in rng.integers(1, 120, 30)] + [big_set(rng, 256, 16, 16)]
    query = big_set(rng, 40, 16, 16)
    whole = similarity.match_batch(query, stack_landmarks(sets))
    for cap in (1 << 24, 5_000, 1):
        monkeypatch.setattr(similarity, 'MATCH_CHUNK_ELEMENTS', cap)
        for got in (similarity.match_sets(query, sets), similarity.match_batch(query, stack_landmarks(sets))):
            np.testing.assert_allclose(got.scores, whole.scores, atol=1e-5)
            assert (got.offsets == whole.offsets).all() and (got.match == whole.match).all()


@pytest.mark.parametrize('center, passes', [(False, 1), ('fuse', 2)], ids=['raw', 'fused'])
def test_one_long_keyframe_and_query_stay_within_the_chunk_bound(center, passes):
    """The issue's case: 99 candidates of 50 landmarks and one of max_landmarks (4096), queried with
    4096 landmarks (D=192): padded, the similarity tensor alone was 100 x 4096 x 4096 floats (6.7 GB).
    Grouped by count and chunked, the traced peak stays within three chunk blocks plus the K x n_a
    results (~48 bytes per candidate and query landmark) of each pass: the fused S (the default)
    matches twice, raw then whitened, and holds the raw pass's results during the second."""
    rng = np.random.default_rng(3)
    sets = [big_set(rng, 50) for _ in range(99)] + [big_set(rng, 4096)]
    query = big_set(rng, 4096)
    tracemalloc.start()
    result = similarity.match_sets(query, sets, center=center)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert result.scores.shape == (100,) and result.scores[-1] > 0
    assert peak < 3 * similarity.MATCH_CHUNK_ELEMENTS * 4 + passes * 100 * 4096 * 48, peak / 2**20
    start = time.perf_counter()
    small = similarity.match_sets(big_set(rng, 50), sets, center=center)
    assert small.scores.shape == (100,)
    print(f'\npeak {peak / 2**20:.0f} MiB; a 50-landmark query after it {1e3 * (time.perf_counter() - start):.0f} ms')


# ----------------------------------------------------------------------------- 3. nested model_info


def nested(depth: int) -> str:
    """A valid model_info text with one value nested `depth` lists deep (never parsed here)."""
    return json.dumps(MODEL)[:-1] + ', "extra": ' + '[' * depth + ']' * depth + '}'


def test_deeply_nested_model_info_is_refused_before_it_is_parsed_or_recorded(tmp_path):
    assert json_shape_problem(json.loads(nested(MODEL_JSON_MAX_DEPTH - 1))) == ''
    for text in (nested(1000), nested(100_000), '[' * 10**6, json.dumps({**MODEL, 'x': 'y' * 70_000})):
        with pytest.raises(ModelError):
            parse_model_json(text)
    store, _ = open_map(tmp_path / 'map.db')
    with store:
        loc = Localizer(store, log=Log())
        loc.model_info(nested(1000))
        assert store.model is None and loc.counters.snapshot() == {'model_info_received': 1, 'bad_model_info': 1}
        loc.model_info(json.dumps(MODEL))
        assert store.model['descriptor_space'] == SPACE


def test_a_map_whose_model_record_nests_deep_is_a_map_error(tmp_path):
    path = tmp_path / 'map.db'
    with MapStore(path, model=MODEL):
        pass
    with sqlite3.connect(path) as con:
        con.execute("UPDATE meta SET value = ? WHERE key = 'model'", (nested(5000),))
    with pytest.raises(MapError, match='bad model record'):
        MapStore(path, create=False)


def test_same_model_with_another_input_height_is_one_clear_error(tmp_path):
    store, _ = open_map(tmp_path / 'map.db')
    with store:
        log = Log()
        loc = Localizer(store, log=log)
        loc.model_info(json.dumps(MODEL))
        for _ in range(3):
            loc.model_info(json.dumps({**MODEL, 'input_height': 480}))
        errors = [t for level, t in log.lines if level == 'ERROR']
        assert len(errors) == 1, log.lines
        assert 'changes input_height from 288 to 480' in errors[0] and '15 rows' in errors[0], errors


# ------------------------------------------------------------------------------------ 4. field count


def cloud_with_fields(n: int) -> PointCloud2:
    msg = msgs.landmarks_to_cloud(make_set(np.random.default_rng(0)))
    extra = [PointField(name=f'x{i}', offset=0, datatype=PointField.UINT8, count=1) for i in range(n)]
    msg.fields = list(msg.fields) + extra
    return msg


def test_point_field_count_is_bounded_and_parsing_linear():
    lset = msgs.cloud_to_landmarks(cloud_with_fields(58))  # 6 + 58 = 64: at the limit
    assert len(lset) == 50
    start = time.perf_counter()
    for decode in (msgs.cloud_to_landmarks, msgs.cloud_to_candidates, msgs.cloud_to_array):
        with pytest.raises(LimitError, match='40006 PointFields is more than max_point_fields 64'):
            decode(cloud_with_fields(40_000))
    assert time.perf_counter() - start < 30  # before: 15 s per decode of 40,000 fields (a loose bound)


# ------------------------------------------------------------------------------- 5. keypoints buffer


def test_pending_keypoints_are_bounded_in_bytes_and_count():
    pending = Pending(max_items=100, max_bytes=1000)
    assert pending.put(1, 'a', 600) == 0 and pending.put(2, 'b', 600) == 1 and pending.nbytes == 600
    assert pending.take(1) is None and pending.take(2) == 'b' and pending.nbytes == 0
    assert sum(pending.put(i, i, 1) for i in range(150)) == 50 and len(pending) == 100


def test_verify_mode_refuses_oversized_keypoints_and_evicts_by_bytes(tmp_path):
    store, _ = open_map(tmp_path / 'map.db', descriptor_space=SPACE)
    with store:
        log = Log()
        loc = Localizer(store, {'verify': True, 'pending_keypoints_bytes': 4 * 2**20}, log=log)
        loc.counters.log = lambda line: log.lines.append(('WARN', line))
        most = loc.limits['max_keypoints'] * KEYPOINT_ROW_BYTES
        for i in range(100):  # the 8 MB messages: refused at arrival, never kept
            loc.keypoints(object(), stamp(i), 8 * 2**20)
        for i in range(100, 120):  # within the per-message bound: kept until the byte budget
            loc.keypoints(object(), stamp(i), most)
        counts = loc.counters.snapshot()
        assert counts['bad_keypoints'] == 100 and loc.pending_keypoints.nbytes <= 4 * 2**20
        assert counts['keypoints_evicted'] == 20 - (4 * 2**20) // most
        assert len([t for _, t in log.lines if 'keypoints_evicted' in t]) == 1, log.lines


# --------------------------------------------------------------------------------- 6. map identity


def test_map_deleted_under_the_store_is_restored_and_loud(tmp_path):
    rng = np.random.default_rng(4)
    sets = [make_set(rng) for _ in range(6)]
    path = tmp_path / 'map.db'
    store = MapStore(path, model=MODEL)
    acknowledged = [store.add(s, (i, 0)) for i, s in enumerate(sets[:3])]
    for f in tmp_path.iterdir():
        os.remove(f)  # rm map.db*, as a user would
    with pytest.raises(MapError, match='was deleted while this node had it open.*3 keyframes were restored'):
        store.add(sets[3], (3, 0))
    acknowledged.append(store.add(sets[4], (4, 0)))  # the next one goes to the restored file
    os.remove(path)
    with pytest.raises(MapError, match='deleted'):
        store.save()
    store.close()
    with MapStore(path, create=False) as again:
        assert set(acknowledged) <= set(again.ids()) and again.check() == []


def test_map_replaced_under_the_store_is_rescued_beside_it(tmp_path):
    rng = np.random.default_rng(5)
    sets = [make_set(rng) for _ in range(3)]
    path, other = tmp_path / 'map.db', tmp_path / 'other.db'
    with MapStore(other, model=MODEL) as o:
        o.add(sets[2], (9, 9))
    store = MapStore(path, model=MODEL)
    acknowledged = [store.add(s, (i, 0)) for i, s in enumerate(sets[:2])]
    os.replace(other, path)
    with pytest.raises(MapError, match='was replaced by another file') as e:
        store.add(sets[2], (2, 0))
    rescued = next(tmp_path.glob('map.db.rescued-*.db'))
    assert str(rescued) in str(e.value)
    for call in (lambda: store.add(sets[2], (2, 0)), store.save, lambda: len(store)):
        with pytest.raises(MapError, match='replaced'):
            call()
    store.close()
    with MapStore(rescued, create=False) as r:
        assert r.ids() == acknowledged and r.check() == []
    with MapStore(path, create=False) as replacement:  # untouched
        assert len(replacement) == 1 and replacement.get(replacement.ids()[0]).meta['stamp'] == (9, 9)


def test_localizer_counts_a_vanished_map_as_keyframes_failed(tmp_path):
    rng = np.random.default_rng(6)
    path = tmp_path / 'map.db'
    store, _ = open_map(path, 'mapping', SPACE)
    with store:
        loc = Localizer(store, {'mode': 'mapping'}, log=Log())
        assert keyframe(loc, make_set(rng), 0) is not None
        os.remove(path)
        assert keyframe(loc, make_set(rng), 1) is None
        assert keyframe(loc, make_set(rng), 2) is not None
        counts = loc.counters.snapshot()
        assert counts['keyframes_failed'] == 1 and counts['keyframes_stored'] == 2
        invariants(counts)


# -------------------------------------------------------------------------------------- 7. smaller


def test_a_query_stamped_ahead_by_more_than_max_query_age_is_stale(tmp_path):
    store, _ = open_map(tmp_path / 'map.db', descriptor_space=SPACE)
    with store:
        loc = Localizer(store, {'max_query_age': 1.0}, log=Log())
        now = stamp(100)
        assert loc.query_fresh(now + 500_000_000, now) and loc.query_fresh(now - 500_000_000, now)
        assert not loc.query_fresh(now + 2 * 10**9, now) and not loc.query_fresh(now - 2 * 10**9, now)
        counts = loc.counters.snapshot()
        assert counts['queries_stale'] == 2 and counts['queries_future'] == 1


def test_period_parameters_have_a_lower_bound():
    from lln_ros.nodes import extractor, matcher
    from lln_ros.nodes.parameters import MIN_PERIOD_S

    for node in (extractor, matcher):
        param = node.PARAMETERS['diagnostics_period']
        assert param.problem(1e-6) and param.problem(MIN_PERIOD_S / 2)
        assert param.problem(0.0) == '' and param.problem(MIN_PERIOD_S) == '' and param.problem(1.0) == ''


def exif_jpeg(image: np.ndarray, orientation: int) -> bytes:
    """A JPEG of image with an EXIF APP1 segment whose Orientation tag (0x0112) is `orientation`."""
    ok, jpg = cv2.imencode('.jpg', image)
    assert ok
    ifd = struct.pack('<H', 1) + struct.pack('<HHIHH', 0x0112, 3, 1, orientation, 0) + struct.pack('<I', 0)
    tiff = b'II*\x00' + struct.pack('<I', 8) + ifd
    app1 = b'Exif\x00\x00' + tiff
    return jpg.tobytes()[:2] + b'\xff\xe1' + struct.pack('>H', len(app1) + 2) + app1 + jpg.tobytes()[2:]


def test_exif_orientation_is_ignored_as_for_a_raw_image():
    image = np.zeros((40, 100, 3), np.uint8)
    image[:, :50] = 255
    data = exif_jpeg(image, 6)  # "rotate 90 CW to display"
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR).shape[:2] == (100, 40)  # OpenCV obeys it
    got, order = msgs.compressed_to_array(CompressedImage(format='jpeg', data=data), max_pixels=10_000)
    assert order == 'bgr' and got.shape[:2] == (40, 100) and msgs.compressed_size(data)[1:] == (100, 40)


# ---------------------------------------------------------------------------------------- 8. guard


def test_guard_counts_internal_error_logs_once_and_returns_the_fallback():
    from lln_ros.nodes.common import failed_response, guarded

    lines = []

    class Node:
        health = Counters(log=lines.append)

        @guarded('query callback')
        def on_query(self, x):
            return 1 / x

        @guarded('~/save', failed_response)
        def on_save(self, request, response):
            raise RecursionError('deep')

    node = Node()
    assert node.on_query(2) == 0.5
    for _ in range(5):
        assert node.on_query(0) is None
    response = node.on_save(None, type('R', (), {'success': True, 'message': ''})())
    assert response.success is False and 'internal_error' in response.message
    assert node.health.snapshot() == {'internal_error': 6}
    assert len(lines) == 2 and 'query callback: unexpected ZeroDivisionError' in lines[0], lines


def test_map_folder_removed_under_the_store_is_restored(tmp_path):
    import shutil

    rng = np.random.default_rng(7)
    path = tmp_path / 'maps' / 'map.db'
    store = MapStore(path, model=MODEL)
    kept = store.add(make_set(rng), (1, 0))
    shutil.rmtree(path.parent)
    with pytest.raises(MapError, match='restored'):
        store.add(make_set(rng), (2, 0))
    store.close()
    with MapStore(path, create=False) as again:
        assert kept in again.ids()
