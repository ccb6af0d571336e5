"""The landmark first stage (lln_ros/core/landmark_index.py): its scoring, its index kept consistent with
both map backends through add / delete / clear / restart, its persisted IVF-PQ file (stale, corrupt,
missing, from another map), and on real images the revisits the holistic top-K misses."""

import logging
import shutil

import numpy as np
import pytest
from test_map_backends import BACKENDS, uri_for
from test_mapstore import MODEL, make_set

from conftest import shared_data
from lln_ros.core.landmark_index import (
    LandmarkIndex,
    check_prefilter,
    decode_ids,
    encode_ids,
    held_count,
    score_hits,
)
from lln_ros.core.landmarks import stack_landmarks
from lln_ros.core.metrics import recall_at_k
from lln_ros.core.retrieval import first_stage
from lln_ros.errors import MapError
from lln_ros.io import datasets
from lln_ros.io.image import load_image
from lln_ros.mapstore import MapStore
from lln_ros.mapstore.index import landmark_disagreements, stale_and_missing

# every landmark held (landmark_index_top 0): these tests count landmarks of 50 per keyframe; the
# default's best 25 have their own tests below
SMALL_IVF = {
    'landmark_index_threshold': 500,
    'landmark_ivf_lists': 8,
    'landmark_nprobe': 8,
    'landmark_pq_bits': 4,
    'landmark_index_top': 0,
}
KINDS = ('ivfpq-fs-refine', 'ivfpq-fs', 'ivfpq')  # the compressed index types (landmark_index.COMPRESSED)


@pytest.fixture
def rng():
    return np.random.default_rng(3)


def test_ids_round_trip_and_prefilter_rule():
    kf, cells = np.array([0, 7, 123456789]), np.array([[0, 0], [11, 8], [4095, 4095]])
    back_kf, back_cells = decode_ids(encode_ids(kf, cells))
    assert back_kf.tolist() == kf.tolist() and back_cells.tolist() == cells.tolist()
    assert decode_ids(np.array([-1]))[0].tolist() == [-1]
    with pytest.raises(ValueError, match='cells'):
        encode_ids(np.array([1]), np.array([[4096, 0]]))
    assert check_prefilter('landmarks', 0) == ('exhaustive', 0)  # backward compatible
    assert check_prefilter('holistic', 30) == ('holistic', 30)
    with pytest.raises(ValueError, match='prefilter must be one of'):
        check_prefilter('fancy', 30)


def test_score_hits_burstiness_and_spatial_consistency():
    """Keyframe 1: 4 query landmarks hit with one consistent offset. Keyframe 2: one query landmark
    hits 4 of its landmarks (a burst) plus 3 hits at scattered offsets, all at a higher cosine.
    Burst and scatter must not outvote the consistent keyframe; hits below tau do not vote."""
    q_cells = np.array([[0, 0], [1, 0], [2, 0], [3, 0], [0, 2], [1, 2], [2, 2]])
    sims = np.full((7, 4), 0.0, np.float32)
    kfs = np.full((7, 4), -1, np.int64)
    m_cells = np.zeros((7, 4, 2), np.int64)
    for i in range(4):  # consistent: offset (-1, 0) for all four
        sims[i, 0], kfs[i, 0], m_cells[i, 0] = 0.8, 1, q_cells[i] + [1, 0]
    sims[0, 1:4], kfs[0, 1:4], m_cells[0, 1:4] = 0.95, 2, [[5, 5], [6, 5], [7, 5]]  # the burst
    for i, off in zip((4, 5, 6), ([3, 0], [-3, 1], [0, -2])):  # scattered
        sims[i, 0], kfs[i, 0], m_cells[i, 0] = 0.95, 2, np.maximum(q_cells[i] + off, 0)
    sims[4, 1], kfs[4, 1] = 0.3, 3  # below tau: keyframe 3 gets nothing
    ids, scores = score_hits(q_cells, sims, kfs, m_cells, {'landmark_tau': 0.5, 'landmark_alpha': 1.0})
    assert ids.tolist() == [1, 2] and scores[0] > scores[1] > 0
    assert scores[0] == pytest.approx(4 * (0.8 - 0.5) / 0.5, rel=1e-5)


def test_index_add_search_remove_and_below(rng):
    index = LandmarkIndex(320)
    sets = [make_set(rng) for _ in range(6)]
    index.add_sets([10, 11, 12, 13, 14, 15], sets)
    held = held_count(50, index.conf)  # the default landmark_index_top (25) of each keyframe's 50
    assert held == 25 and index.ntotal == 6 * held and index.keyframe_counts() == {i: held for i in range(10, 16)}
    ids, scores = index.shortlist(make_set(rng, base=sets[2], noise=0.05), k=3)
    assert ids[0] == 12 and scores[0] > 0
    ids, _ = index.shortlist(sets[4], k=3, below=14)  # keyframes 14, 15 are excluded
    assert 14 not in ids and 15 not in ids
    assert index.remove_keyframes([12, 99]) == held and 12 not in index.keyframe_counts()


def test_disagreements_name_what_a_store_catches_up(rng):
    """What both backends catch up at open and the integrity check reports: keyframes held in another
    number than their stored landmarks are due (stale), stored but not held (missing), held but not
    stored; a keyframe with nothing due and nothing held agrees."""
    index = LandmarkIndex(320)
    index.add_sets([1, 2, 3], [make_set(rng) for _ in range(3)])  # 25 held each (landmark_index_top)
    stored = {1: 50, 2: 10, 4: 50, 5: 0}  # 2 is due 10, 3 is not stored, 4 is not held, 5 has none
    wrong = landmark_disagreements(index, stored)
    assert wrong == {2: (25, 10), 3: (25, 0), 4: (0, 25)}
    assert stale_and_missing(wrong) == ([2, 3], [2, 4])
    assert landmark_disagreements(index, {1: 50, 2: 30, 3: 25}) == {}


def test_query_top_searches_only_the_best_query_landmarks(rng):
    """landmark_query_top m: the first m query landmarks (the best by score) search, centred on the
    mean of all of them as without the cap, so their hits are the uncapped search's first m rows."""
    index = LandmarkIndex(320, {'landmark_query_top': 0})
    sets = [make_set(rng) for _ in range(6)]
    index.add_sets(list(range(6)), sets)
    query = make_set(rng, base=sets[2], noise=0.05)
    sims, kf, cells = index.search(query.descriptors, 5)
    top_sims, top_kf, top_cells = index.search(query.descriptors, 5, top=10)
    assert sims.shape == (50, 5) and top_sims.shape == (10, 5)
    np.testing.assert_allclose(top_sims, sims[:10], rtol=1e-6)
    assert (top_kf == kf[:10]).all() and (top_cells == cells[:10]).all()
    capped = LandmarkIndex(320, {'landmark_query_top': 10})
    capped.add_sets(list(range(6)), sets)
    ids, scores = capped.shortlist(query, k=3)
    assert ids[0] == 2 and scores[0] > 0
    assert scores[0] < index.shortlist(query, k=3)[1][0]  # 10 landmarks vote, not 50


def test_index_top_holds_each_keyframes_best_landmarks_centred_on_all(rng):
    """landmark_index_top m: the index holds the first m stored landmarks of each keyframe (the best by
    score), each the same vector as an uncapped index holds (centred on all of its keyframe's), and
    held_count is what the stores check against."""
    sets = [make_set(rng, n=int(n)) for n in (50, 8, 30)]
    full, top = LandmarkIndex(320, {'landmark_index_top': 0}), LandmarkIndex(320, {'landmark_index_top': 10})
    for index in (full, top):
        index.add_sets([4, 5, 6], sets)
    counts = {i: held_count(len(s), top.conf) for i, s in zip((4, 5, 6), sets)}
    assert top.keyframe_counts() == {4: 10, 5: 8, 6: 10} == counts
    held = np.sort(top.landmark_ids())
    want = np.sort(
        np.concatenate([encode_ids(np.full(min(len(s), 10), i), s.cells[:10]) for i, s in zip((4, 5, 6), sets)])
    )
    assert held.tolist() == want.tolist()
    np.testing.assert_allclose(
        [top.index.reconstruct(int(i)) for i in held], [full.index.reconstruct(int(i)) for i in held], atol=1e-6
    )
    top.build(
        np.concatenate([s.descriptors for s in sets]),
        np.concatenate([encode_ids(np.full(len(s), i), s.cells) for i, s in zip((4, 5, 6), sets)]),
    )
    assert np.sort(top.landmark_ids()).tolist() == want.tolist()  # build holds the same rows as add


@pytest.mark.parametrize('kind', ['exact', 'ivfpq-fs'])
def test_centering_ignores_what_every_landmark_of_an_image_shares(kind):
    """The query's 12 landmarks are 12 places seen under one strong condition (a component every
    landmark of the image shares: snow, dusk). Keyframe 1 holds the same places under another
    condition; keyframe 2 other places under the query's condition. On raw descriptors the shared
    condition outvotes the places and keyframe 2 leads; centred (landmark_center, the default) on
    each image's mean, keyframe 1 does. Many filler keyframes make the compressed index train."""
    rng = np.random.default_rng(7)
    d, n = 64, 12

    def unit(x):
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    places, others = unit(rng.standard_normal((n, d))), unit(rng.standard_normal((n, d)))
    winter, summer = 2.0 * unit(rng.standard_normal(d)), 2.0 * unit(rng.standard_normal(d))
    cells = np.stack([np.arange(n) % 4, np.arange(n) // 4], axis=1)
    query = unit(places + winter + 0.05 * rng.standard_normal((n, d)))
    sets = [unit(places + summer), unit(others + winter)]
    sets += [unit(rng.standard_normal((n, d)) + c) for c in (winter, summer) for _ in range(30)]
    found = {}
    for center in (False, True):
        conf = {'landmark_center': center, 'landmark_tau': 0.35 if not center else 0.0}
        if kind != 'exact':
            conf.update(
                {
                    'landmark_index_threshold': 100,
                    'landmark_ivf_lists': 4,
                    'landmark_nprobe': 4,
                    'landmark_compressed': kind,
                }
            )
        index = LandmarkIndex(d, conf)
        index.add(np.concatenate(sets), np.repeat(np.arange(1, len(sets) + 1), n), np.tile(cells, (len(sets), 1)))
        assert index.kind == kind
        sims, kfs, map_cells = index.search(query, 20)
        found[center] = score_hits(cells, sims, kfs, map_cells, index.conf)[0][0]
    assert found == {False: 2, True: 1}


@pytest.mark.parametrize('compressed', KINDS)
def test_index_type_switch_remove_reset_and_file(compressed, tmp_path, rng):
    """Exact up to landmark_index_threshold, the configured compressed type once add() crosses it
    (re-trained from what it held); a range remove (<= 4 keyframes) and a batch remove (more) both
    leave exactly the other keyframes; reset is exact and empty; write / read keeps type, nprobe and
    contents; growth past landmark_retrain_factor x the training size asks the owner to rebuild."""
    conf = {**SMALL_IVF, 'landmark_compressed': compressed, 'landmark_retrain_factor': 2}
    index = LandmarkIndex(320, conf)
    sets = [make_set(rng) for _ in range(24)]
    index.add_sets(range(8), sets[:8])
    assert index.kind == 'exact' and index.ntotal == 400  # 400 <= 500: still exact
    index.add_sets(range(8, 12), sets[8:12])  # trained on keyframes 0-10 (550 > 500), then 11 added
    assert index.kind == compressed and index.trained_on == 550 and not index.needs_rebuild()
    assert index.keyframe_counts() == {i: 50 for i in range(12)}
    ids, _ = index.shortlist(make_set(rng, base=sets[9], noise=0.05), k=3)
    assert ids[0] == 9
    assert index.remove_keyframes([3]) == 50 and index.remove_keyframes([0, 1, 2, 4, 5]) == 250
    assert sorted(index.keyframe_counts()) == [6, 7, 8, 9, 10, 11]
    assert 3 not in index.shortlist(sets[3], k=6)[0]
    index.write(str(tmp_path / 'x.landmarks'), {'map_uuid': 'u'})
    back, header = LandmarkIndex.read(str(tmp_path / 'x.landmarks'), 320, conf)
    assert back.kind == compressed and back.index.nprobe == 8 and header['map_uuid'] == 'u'
    assert back.keyframe_counts() == index.keyframe_counts() and back.trained_on == 550
    index.add_sets(range(12, 24), sets[12:24])  # 900 landmarks: 1.6 x 550
    assert not index.needs_rebuild()
    index.add_sets(range(24, 31), [make_set(rng) for _ in range(7)])  # 1250 > 2 x 550
    assert index.needs_rebuild()
    index.reset()
    assert index.kind == 'exact' and index.ntotal == 0
    with pytest.raises(ValueError, match='landmark_compressed must be one of'):
        LandmarkIndex(320, {**conf, 'landmark_compressed': 'hnsw'}).build(
            np.zeros((600, 320), np.float32), np.arange(600)
        )


@pytest.mark.parametrize('compressed', KINDS)
def test_compressed_index_does_not_depend_on_batching(compressed, rng):
    """One add of a whole map (lln-eval) and one add per keyframe (a matcher growing its map) train
    the compressed index on the same landmarks, so both answer every query alike."""
    conf = {**SMALL_IVF, 'landmark_compressed': compressed}
    sets = [make_set(rng, n=int(n)) for n in rng.integers(20, 51, 30)]
    whole, grown = LandmarkIndex(320, conf), LandmarkIndex(320, conf)
    whole.add_sets(range(30), sets)
    for i, s in enumerate(sets):
        grown.add_sets([i], [s])
    assert whole.kind == grown.kind == compressed and whole.trained_on == grown.trained_on
    assert whole.trained_on == next(t for t in np.cumsum([len(s) for s in sets]) if t > 500)
    for s in sets[::3]:
        q = make_set(rng, n=len(s), base=s, noise=0.1)
        assert np.array_equal(whole.shortlist(q, k=5)[0], grown.shortlist(q, k=5)[0])


@pytest.mark.parametrize('index', ['exact', 'ivfpq-fs', 'ivfpq-fs top 25'])
@pytest.mark.parametrize('kind', BACKENDS)
def test_map_keeps_landmark_index_consistent(kind, index, tmp_path, rng):
    """add / delete / clear / reopen: the landmark index always holds exactly the stored landmarks
    (with landmark_index_top 25: each keyframe's best 25), and the landmark first stage answers with
    the right keyframe -- exact, and compressed (the threshold lowered to 300 landmarks, so the map
    crosses it while growing and at reopen; 200 with the best 25)."""
    uri = uri_for(kind, tmp_path)
    sets = [make_set(rng, n=int(n)) for n in rng.integers(20, 51, 12)]
    index, _, top = index.partition(' top ')
    threshold = 200 if top else 300  # crossed by the 12 keyframes' ~290 best-25 landmarks too
    conf = (
        {} if index == 'exact' else {**SMALL_IVF, 'landmark_index_threshold': threshold, 'landmark_compressed': index}
    )
    conf['landmark_index_top'] = int(top or 0)

    def held(chosen):  # info()'s 'landmarks': what the landmark index holds
        return sum(min(len(s), int(top or len(s))) for s in chosen)

    with MapStore.open(uri, model=MODEL, conf=conf) as store:
        ids = store.add_many(sets[:8], [(i, 0) for i in range(8)])
        ids += [store.add(s, (100 + i, 0)) for i, s in enumerate(sets[8:])]
        assert store.info()['landmarks'] == held(sets) and store.check() == []
        assert store.info()['landmark_index'] == index
        assert (
            store.query(make_set(rng, n=len(sets[5]), base=sets[5], noise=0.1), prefilter='landmarks')[0].keyframe_id
            == ids[5]
        )
        store.delete([ids[5], ids[9]])
        assert store.info()['landmarks'] == held(s for i, s in enumerate(sets) if i not in (5, 9))
        assert all(c.keyframe_id not in (ids[5], ids[9]) for c in store.query(sets[5], prefilter_k=12, k=12))
        assert store.check() == []
    with MapStore.open(uri, conf=conf) as store:  # restart: rebuilt (or loaded) and checked
        assert store.info()['landmarks'] == held(s for i, s in enumerate(sets) if i not in (5, 9))
        assert store.check() == [] and store.info()['landmark_index'] == index
        assert store.query(sets[3])[0].keyframe_id == ids[3]
        assert store.clear() == 10 and store.info()['landmarks'] == 0 and store.query(sets[3]) == []
        assert store.info()['landmark_index'] == 'exact'  # cleared: exact again until it regrows
        new = store.add(sets[3])
        assert store.query(sets[3])[0].keyframe_id == new and store.check() == []


@pytest.mark.parametrize('compressed', KINDS)
def test_compressed_index_persisted_stale_corrupt_missing_foreign(compressed, tmp_path, rng, caplog):
    """Compressed maps (threshold lowered to 500 landmarks) persist their index next to the map; a
    stale file is caught up, a corrupt / missing / foreign one, or one of raw descriptors (an older
    lln_ros), rebuilt with a warning, never silently empty."""
    SMALL_IVF = {**globals()['SMALL_IVF'], 'landmark_compressed': compressed}
    path = str(tmp_path / 'map.db')
    sets = [make_set(rng) for _ in range(30)]
    with MapStore.open(path, model=MODEL, conf=SMALL_IVF) as store:
        ids = store.add_many(sets[:25], [(i, 0) for i in range(25)])
        assert store.info()['landmark_index'] == compressed
        store.save()
        stale = tmp_path / 'stale.landmarks'
        shutil.copy(store.landmark_path, stale)
        ids += store.add_many(sets[25:], [(i, 0) for i in range(25, 30)])
        store.delete([ids[0]])
    lm_path = path + '.landmarks'
    shutil.copy(stale, lm_path)  # as after a crash: 5 keyframes behind, 1 deleted
    with caplog.at_level(logging.INFO, logger='lln_ros.mapstore'):
        with MapStore.open(path, conf=SMALL_IVF) as store:
            assert 'caught up (5 keyframes added, 1 removed)' in caplog.text
            assert store.info()['landmarks'] == 29 * 50 and store.check() == []
            assert store.query(make_set(rng, base=sets[27], noise=0.05))[0].keyframe_id == ids[27]
    data = bytearray(open(lm_path, 'rb').read())
    data[len(data) // 2 : len(data) // 2 + 64] = b'\x00' * 64
    open(lm_path, 'wb').write(bytes(data))
    with pytest.raises(MapError, match='checksum'):
        LandmarkIndex.read(lm_path, 320)
    for damage in ('corrupt', 'missing', 'foreign', 'raw'):
        if damage == 'missing':
            (tmp_path / 'map.db.landmarks').unlink()
        if damage == 'raw':  # written by an lln_ros before landmark_center: uncentred vectors
            with MapStore.open(path, conf={**SMALL_IVF, 'landmark_center': False}) as store:
                pass
            with pytest.raises(MapError, match='raw descriptors; landmark_center is True'):
                LandmarkIndex.read(lm_path, 320)
        if damage == 'foreign':
            with MapStore.open(str(tmp_path / 'other.db'), model=MODEL, conf=SMALL_IVF) as other:
                other.add_many(sets[:20], [(i, 0) for i in range(20)])
            shutil.copy(str(tmp_path / 'other.db.landmarks'), lm_path)
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger='lln_ros.mapstore'):
            with MapStore.open(path, conf=SMALL_IVF) as store:
                assert 'rebuilding it from the map' in caplog.text, damage
                assert store.info()['landmarks'] == 29 * 50 and store.check() == []
                assert store.query(sets[12])[0].keyframe_id == ids[12]


def test_refine_kind_recalls_exact_neighbours_better_on_real_landmarks(extractor):
    """Real landmarks (Nordland test split: 240 summer images as the map, 24 winter ones as queries),
    prepared as the shipped index holds them (centred, whitened): the top-1 neighbour of each query
    landmark under 'ivfpq-fs-refine' (4-bit fast-scan shortlist of 8 x knn re-ranked on SQ6 codes,
    nprobe 64) is the exact one clearly more often than under 'ivfpq-fs' (the fast-scan codes alone,
    nprobe 16), every landmark held, among the knn the first stage asks for (measured 2026-12-06:
    0.80 against 0.72 of 1,200 query landmarks). The shipped refine setting (best 25, SQ8, k_factor
    4, nprobe 56) is chosen at 100k keyframes by bench/bench_landmark_index.py."""
    root = shared_data('nordland_trimmed')
    ds = datasets.parse_spec(f'aligned:{root / "summer"},{root / "winter"},1', (0.7, 0.7 + 240 / 3576))
    refs = extractor.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    qs = extractor.extract_batch([load_image(str(p)) for p in ds.query_paths[::10]])
    space = extractor.descriptor_space
    every = {'landmark_index_top': 0}
    exact = LandmarkIndex(refs[0].dim, {**every, 'landmark_index_threshold': 10**9}, space)
    exact.add_sets(range(len(refs)), refs)
    queries = [exact.prepare(q.descriptors) for q in qs]  # as search() prepares a query
    knn = exact.conf['landmark_knn']  # the first stage asks for knn neighbours; its top 1 is compared
    truth = np.concatenate([exact.search_prepared(q, knn)[1][:, 0] for q in queries])
    recall = {}
    for kind in ('ivfpq-fs-refine', 'ivfpq-fs'):
        conf = {**every, 'landmark_index_threshold': 0, 'landmark_compressed': kind}
        if kind == 'ivfpq-fs-refine':
            conf.update({'landmark_refine': 'SQ6', 'landmark_k_factor': 8, 'landmark_nprobe': 64})
        index = LandmarkIndex(refs[0].dim, conf, space)
        index.add_sets(range(len(refs)), refs)
        assert index.kind == kind and index.ntotal == exact.ntotal
        got = np.concatenate([index.search_prepared(q, knn)[1][:, 0] for q in queries])
        recall[kind] = float(np.mean(got == truth))
    assert recall['ivfpq-fs-refine'] >= recall['ivfpq-fs'] + 0.04, recall


def test_a_file_of_another_kind_still_reads_and_a_map_rebuilds_it(tmp_path, rng, caplog):
    """An 'ivfpq-fs' file (the default of earlier lln_ros) still reads under a conf asking for that
    kind; under one asking for 'ivfpq-fs-refine' it is refused (MapError) and the map store rebuilds
    its index as the asked kind, with a warning, holding every stored landmark."""
    path = str(tmp_path / 'map.db')
    sets = [make_set(rng) for _ in range(30)]
    old = {**SMALL_IVF, 'landmark_compressed': 'ivfpq-fs'}
    new = {**SMALL_IVF, 'landmark_compressed': 'ivfpq-fs-refine'}
    with MapStore.open(path, model=MODEL, conf=old) as store:
        ids = store.add_many(sets, [(i, 0) for i in range(30)])
    back, _ = LandmarkIndex.read(path + '.landmarks', 320, old)
    assert back.kind == 'ivfpq-fs' and back.ntotal == 30 * 50
    with pytest.raises(MapError, match='is ivfpq-fs; landmark_compressed is ivfpq-fs-refine'):
        LandmarkIndex.read(path + '.landmarks', 320, new)
    with caplog.at_level(logging.WARNING, logger='lln_ros.mapstore'):
        with MapStore.open(path, conf=new) as store:
            assert 'rebuilding it from the map' in caplog.text
            assert store.info()['landmark_index'] == 'ivfpq-fs-refine' and store.check() == []
            assert store.query(make_set(rng, base=sets[7], noise=0.05))[0].keyframe_id == ids[7]
    back, header = LandmarkIndex.read(path + '.landmarks', 320, new)
    assert header['kind'] == 'ivfpq-fs-refine' and back.refine.n == back.ntotal == 30 * 50
    with pytest.raises(MapError, match='re-ranks on SQ8; landmark_refine is SQ6'):  # SQ8: the default
        LandmarkIndex.read(path + '.landmarks', 320, {**new, 'landmark_refine': 'SQ6'})
    fewer = {**new, 'landmark_index_top': 20}  # another landmark_index_top: refused, rebuilt
    with pytest.raises(MapError, match='best 0 landmarks of each keyframe .0 = all.; landmark_index_top is 20'):
        LandmarkIndex.read(path + '.landmarks', 320, fewer)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger='lln_ros.mapstore'):
        with MapStore.open(path, conf=fewer) as store:
            assert 'rebuilding it from the map' in caplog.text and store.check() == []
            assert store.info()['landmarks'] == 30 * 20  # what the index holds
            assert store.query(make_set(rng, base=sets[9], noise=0.05))[0].keyframe_id == ids[9]


def _rtabmap_sets(extractor):
    root = shared_data('rtabmap_loop')
    ds = datasets.parse_spec(f'loop:{root},{root / "samples_GT.bmp"}')
    sets = extractor.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    return ds, sets


def _holistic_misses_found(qs, refs, gt, allowed, k):
    batch = stack_landmarks(refs)
    lm, _ = first_stage(qs, batch, k, 'landmarks', allowed)
    hol, _ = first_stage(qs, batch, k, 'holistic', allowed)

    def hit(r):
        return ((r >= 0) & np.take_along_axis(gt, np.maximum(r, 0), axis=1)).any(1)

    return lm, hol, int((hit(lm) & ~hit(hol)).sum()), int((hit(hol) & ~hit(lm)).sum())


def test_rtabmap_landmark_first_stage_finds_revisits(extractor):
    """rtabmap_loop (real office walk, 44 loop queries): the landmark top-2 holds a true revisit for
    more loop queries than the holistic top-2 (measured: 42 vs 41 of 44, the one more is a revisit
    the holistic top-2 misses; both hold 43 at K = 3)."""
    ds, sets = _rtabmap_sets(extractor)
    lm, hol, found, lost = _holistic_misses_found(sets, sets, ds.gt, ds.candidates, 2)
    assert recall_at_k(lm, ds.gt, 2) > recall_at_k(hol, ds.gt, 2)
    assert found >= 1 and found > lost, (found, lost)


def test_nordland_slice_landmark_first_stage_beats_holistic(extractor):
    """80 places of the Nordland test split (winter queries, summer map): the landmark first stage
    holds a true match (+-1 frame) in its top 5 for clearly more queries than the holistic top 5."""
    root = shared_data('nordland_trimmed')
    ds = datasets.parse_spec(f'aligned:{root / "summer"},{root / "winter"},1', (0.8, 0.8 + 80 / 3576))
    refs = extractor.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    qs = extractor.extract_batch([load_image(str(p)) for p in ds.query_paths])
    lm, hol, found, lost = _holistic_misses_found(qs, refs, ds.gt, None, 5)
    assert recall_at_k(lm, ds.gt, 5) > recall_at_k(hol, ds.gt, 5) + 0.1, (
        recall_at_k(lm, ds.gt, 5),
        recall_at_k(hol, ds.gt, 5),
    )
    assert found > lost
