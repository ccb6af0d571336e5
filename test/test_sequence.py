"""lln_ros.core.sequence and lln_ros.peers: the sequence search (offline = online), its stream faults, the
SeqSLAM front end, and lln-eval's sad / seqslam / X+seq rows on real data."""

import json

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.cli.eval import main
from lln_ros.core import retrieval
from lln_ros.core.sequence import (
    KeyframeSequence,
    SequenceError,
    SequenceMatcher,
    acquiring,
    contrast_enhance,
    rank_sequences,
    sad_descriptors,
    sad_difference,
    sad_size,
    standardise,
)
from lln_ros.errors import LLNError

S = 10**9  # ns per second


def route_scores(n_q=60, n_r=80, k=8, seed=0, true_score=0.5, noise=0.6):
    """Single-frame top-k of a vehicle driving a mapped route at 1 map frame per query (query q is at
    map frame q + 5): the true frame scores `true_score`, k-1 distractors score uniformly in
    [0, noise) at random places. With noise > true_score single frames are often wrong."""
    rng = np.random.default_rng(seed)
    ranked = np.zeros((n_q, k), np.int64)
    scores = np.zeros((n_q, k), np.float32)
    for q in range(n_q):
        others = rng.choice(np.setdiff1d(np.arange(n_r), [q + 5]), k - 1, replace=False)
        ranked[q] = np.r_[q + 5, others]
        scores[q] = np.r_[true_score, rng.uniform(0, noise, k - 1)]
        order = np.argsort(-scores[q], kind='stable')
        ranked[q], scores[q] = ranked[q][order], scores[q][order]
    return ranked, scores, np.arange(n_q) + 5


def test_sequence_recovers_the_route_single_frames_miss():
    ranked, scores, truth = route_scores()
    single = (ranked[:, 0] == truth).mean()
    seq_ranked, seq_scores = rank_sequences(ranked, scores, 80, {'length': 10}, k=5)
    seq = (seq_ranked[10:, 0] == truth[10:]).mean()  # after the window has filled
    assert single < 0.6 and seq == 1.0, (single, seq)
    assert np.all(np.diff(seq_scores, axis=1) <= 0)  # best first


def test_online_keyframe_ids_give_the_offline_figures():
    """KeyframeSequence (the node's) over non-contiguous keyframe ids = rank_sequences over positions."""
    ranked, scores, _ = route_scores(seed=1)
    offline, offline_scores = rank_sequences(ranked, scores, 80, {'length': 10}, k=5)
    ids = np.arange(80) * 3 + 7  # ids grow with insertion but skip values (a cleared map never reuses ids)
    online = KeyframeSequence({'length': 10})
    online.set_map(ids)
    for q in range(len(ranked)):
        reason, out = online.update(q * S // 20, dict(zip(ids[ranked[q]].tolist(), scores[q].tolist())), k=5)
        assert reason is None
        assert [kf for kf, _ in out] == ids[offline[q]].tolist()
        np.testing.assert_allclose([s for _, s in out], offline_scores[q], rtol=1e-6)
    assert len(online.matcher) == 10  # the ring never grows past L


def test_carry_offline_equals_online_and_keeps_a_lost_route():
    """rank_sequences with carry and score_of (lln-eval) = KeyframeSequence.ahead + update (the matcher),
    and carrying finds the route where the single-frame top-k often misses it."""
    rng = np.random.default_rng(5)
    n_q, n_r, k = 60, 80, 6
    dense = rng.uniform(0, 0.6, (n_q, n_r))  # S of every query and map frame; query q is at frame q + 5
    dense[np.arange(n_q), np.arange(n_q) + 5] = 0.5
    ranked = np.argsort(-dense, axis=1, kind='stable')[:, :k]  # the true frame is often not in the top k
    scores = np.take_along_axis(dense, ranked, 1).astype(np.float32)
    score_of = lambda q, refs: dense[q, refs]  # noqa: E731
    conf = {'length': 10}
    off, off_scores = rank_sequences(ranked, scores, n_r, conf, k=5, carry=10, score_of=score_of)
    plain, _ = rank_sequences(ranked, scores, n_r, conf, k=5)
    ids = np.arange(n_r) * 2 + 3
    online = KeyframeSequence(conf)
    online.set_map(ids)
    for q in range(n_q):
        extra = (online.ahead() - 3) // 2
        extra = extra[~np.isin(extra, ranked[q])]
        given = dict(zip(ids[ranked[q]].tolist(), scores[q].tolist())) | dict(zip(ids[extra].tolist(), dense[q, extra]))
        _, out = online.update(q * S // 20, given, k=5, carry=10)
        assert [kf for kf, _ in out] == ids[off[q]].tolist(), q
        np.testing.assert_allclose([s for _, s in out], off_scores[q], rtol=1e-6)
    truth = np.arange(n_q) + 5
    in_top = np.mean([truth[q] in ranked[q] for q in range(n_q)])
    assert in_top < 0.6 and (off[20:, 0] == truth[20:]).mean() > (plain[20:, 0] == truth[20:]).mean(), in_top


def test_interleaved_sessions_give_each_session_its_own_route():
    """Two robots writing one map interleave their ids (issue 29): with their origins, each session's
    keyframes are one route, and the figures are those of that session's map alone, whatever the
    interleaving, and also when the other robot's keyframes join while the window is full."""
    from lln_ros.mapstore.sessions import Origin

    ranked, scores, _ = route_scores(seed=1)
    offline, offline_scores = rank_sequences(ranked, scores, 80, {'length': 10}, k=5)
    rng = np.random.default_rng(3)
    owner = rng.permutation(np.r_[np.zeros(80, int), np.ones(60, int)])  # robot A: 80 keyframes, B: 60
    ids = np.arange(1, 141)
    a_ids, b_ids = ids[owner == 0], ids[owner == 1]
    origins = {int(k): Origin(2, i + 1) for i, k in enumerate(a_ids)}
    origins |= {int(k): Origin(1, i + 1) for i, k in enumerate(b_ids)}  # B's session comes first
    online = KeyframeSequence({'length': 10})
    online.set_map(a_ids, {k: o for k, o in origins.items() if k in set(a_ids.tolist())})
    for q in range(len(ranked)):
        if q == 30:  # B's keyframes join inside the route, before A's: the window is re-mapped by id
            online.set_map(ids, {k: o for k, o in origins.items() if k in set(b_ids.tolist())})
            assert online.ids[:60].tolist() == b_ids.tolist() and len(online.matcher) == 10
        reason, out = online.update(q * S // 20, dict(zip(a_ids[ranked[q]].tolist(), scores[q].tolist())), k=5)
        assert reason is None
        assert [kf for kf, _ in out] == a_ids[offline[q]].tolist()
        np.testing.assert_allclose([s for _, s in out], offline_scores[q], rtol=1e-6)
    # in id order (no origins) the lines cross the interleaving: the answers differ
    plain = KeyframeSequence({'length': 10})
    plain.set_map(ids)
    differ = 0
    for q in range(len(ranked)):
        _, out = plain.update(q * S // 20, dict(zip(a_ids[ranked[q]].tolist(), scores[q].tolist())), k=5)
        differ += [kf for kf, _ in out][:1] != a_ids[offline[q]].tolist()[:1]
    assert differ > 0


def test_excluded_ids_are_never_answers():
    ks = KeyframeSequence({'length': 3})
    ks.set_map([1, 2, 3, 4, 5])
    _, out = ks.update(0, {4: 0.9, 5: 1.0, 2: 0.1}, excluded=[5, 4], k=5)
    assert {kf for kf, _ in out} <= {1, 2, 3} and out


def test_ahead_is_where_the_best_lines_go_next():
    """carry: the best ends are kept; ahead() gives each end's route position + 0 .. ceil(v_max) as
    ids, within the map; nothing before a search or with carry 0."""
    route = [10, 20, 30, 40, 50, 60]  # no origins: route order is id order
    ks = KeyframeSequence({'length': 3, 'score_norm': 'none'})  # v_max 1.2: steps 0, 1, 2
    ks.set_map(route[::-1])
    assert len(ks.ahead()) == 0
    ks.update(0, {30: 0.2, 20: 0.9}, k=1)
    assert len(ks.ahead()) == 0  # carry 0: nothing kept
    _, out = ks.update(S // 10, {20: 0.1, 40: 0.9}, k=1, carry=2)
    assert len(out) == 1 and ks.carried.tolist() == [40, 30]  # the two best ends, best first
    assert ks.ahead().tolist() == [30, 40, 50, 60]  # 30, 40, 50 and 40, 50, 60


def test_stream_faults_reset_the_window():
    seq = SequenceMatcher({'length': 4, 'max_gap_s': 0.5})
    assert seq.push(1 * S, [1], [0.5]) is None
    assert seq.push(1 * S + S // 4, [2], [0.5]) is None  # 0.25 s: a dropped frame, absorbed
    assert len(seq) == 2
    assert seq.push(1 * S, [3], [0.5]) == 'out_of_order'  # older than the last: new sequence
    assert len(seq) == 1
    assert seq.push(1 * S, [4], [0.5]) == 'out_of_order'  # a repeated stamp too
    assert seq.push(3 * S, [5], [0.5]) == 'gap'  # 2 s of nothing: new sequence
    assert len(seq) == 1 and seq.resets == {'out_of_order': 2, 'gap': 1}
    for i in range(10):
        seq.push(4 * S + i, [i], [0.1])
    assert len(seq) == 4


def test_length_longer_than_the_map_is_defined():
    """L = 10 on a 3-frame map: positions off the map count as the row's lowest score."""
    seq = SequenceMatcher({'length': 10, 'v_min': 1, 'v_max': 1, 'v_steps': 1, 'score_norm': 'none'})
    for q in range(10):
        seq.push(q, [0, 1, 2], [0.1, 0.2, 0.9 if q == 9 else 0.3])
    ends, values = seq.search(3)
    assert ends[0] == 2
    # line ending at 2: rows b = 0, 1, 2 visit 2, 1, 0 (0.9, 0.2, 0.1); b = 3..9 are off the map (0.1)
    assert values[0] == pytest.approx((0.9 + 0.2 + 0.1 + 7 * 0.1) / 10)


@pytest.mark.parametrize('norm, on_route_min, lost_max', [('none', 0.5, 0.3), ('zscore', 3.0, 1.0)])
def test_jump_to_an_unmapped_area_lowers_the_sequence_score(norm, on_route_min, lost_max):
    """In raw S (none) and in standard deviations above each query's lowest candidate (zscore)."""
    ranked, scores, truth = route_scores(n_q=30, noise=0.3)
    seq = SequenceMatcher({'length': 10, 'score_norm': norm})
    for q in range(30):
        seq.push(q, ranked[q], scores[q])
    _, on_route = seq.search(80, k=1)
    for q in range(30, 40):  # unmapped: every candidate is a weak, random match
        rng = np.random.default_rng(q)
        seq.push(q, rng.choice(80, 8, replace=False), rng.uniform(0, 0.3, 8))
    _, lost = seq.search(80, k=1)
    assert on_route[0] >= on_route_min > lost_max >= lost[0]  # a min_score between the two says "new place"


def test_standardise_puts_each_query_in_its_own_units():
    """zscore: standard deviations above the row's lowest score, so the floor (unscored) is 0, a
    sequence score is never negative, and a row that does not spread counts for nothing."""
    z = standardise(np.array([2.0, 4.0, 6.0]))
    assert z.min() == 0 and z.std() == pytest.approx(1.0) and z.tolist() == pytest.approx([0, 1.2247, 2.4495], 1e-4)
    assert standardise(np.array([0.7, 0.7])).tolist() == [0, 0]
    assert standardise(np.zeros(0)).shape == (0,)
    assert standardise(np.array([1e308, -1e308])).tolist() == [0, 0]  # no spread in float range: no NaN
    seq = SequenceMatcher({'length': 2, 'score_norm': 'zscore'})
    seq.push(0, [1, 2], [100.0, 300.0])  # the same ranking at 100x the scale: the same row
    seq.push(1, [2, 3], [1.0, 3.0])
    assert seq.ring[0][2].tolist() == seq.ring[1][2].tolist() == [0, 2]
    assert (seq.search(5)[1] >= 0).all()


def best_end_by_norm(rows: list, map_size: int) -> dict:
    """{score_norm: the best sequence end} after pushing rows [(positions, scores), ...] in order into a
    search as long as the rows, at velocity 1 only."""
    best = {}
    for norm in ('none', 'zscore'):
        seq = SequenceMatcher({'length': len(rows), 'v_min': 1, 'v_max': 1, 'v_steps': 1, 'score_norm': norm})
        for q, (pos, sc) in enumerate(rows):
            seq.push(q, pos, sc)
        best[norm] = int(seq.search(map_size, k=1)[0][0])
    return best


def test_zscore_keeps_one_widely_spread_query_from_outvoting_the_route():
    """Five queries on a route (map positions 10..14) whose true frame is their best candidate by a
    small margin, and one query whose S happens to spread widely, with a wrong frame (40) far above its
    others: averaged raw, that one query's outlier outvotes four agreeing ones; in each query's own
    units (zscore) the route wins."""
    rows = []
    for q in range(5):
        others = [30 + q, 20 + q, 45 - q]
        rows.append(([10 + q, *others], [0.6, 0.5, 0.52, 0.55]))
    rows[2] = ([40, 12, 31, 21], [5.0, 0.6, 0.5, 0.45])
    assert best_end_by_norm(rows, 50) == {'none': 42, 'zscore': 14}


def test_zscore_gives_frames_that_revisit_nothing_full_weight():
    """Why 'none' is the default: at a loop's first revisit (map 0..3; two frames of places not in the
    map, then place 1 again), raw S keeps the two unmatched frames quiet and the revisit answers 1;
    standardised, their noise weighs as much as the revisit, and a line through it wins (the
    mapping-mode node test and rtabmap_loop's query 45 show the same, docs/benchmarks.md)."""
    rows = [[0.10, 0.12, 0.11, 0.13], [0.10, 0.11, 0.14, 0.12], [0.20, 0.90, 0.30, 0.25]]
    assert best_end_by_norm([([0, 1, 2, 3], sc) for sc in rows], 4) == {'none': 1, 'zscore': 3}
    assert SequenceMatcher().conf['score_norm'] == 'none'  # the default, literally


def test_allowed_ends_and_bad_conf():
    seq = SequenceMatcher({'length': 3})
    seq.push(0, [5], [1.0])
    seq.push(1, [6], [1.0])
    ends, _ = seq.search(10, allowed_ends=np.arange(10) < 7)  # v in 0.8..1.2: a line through 5 ends at 6
    assert ends.tolist() == [6]
    ends, _ = seq.search(10, allowed_ends=np.arange(10) < 5)
    assert len(ends) == 0  # no line through a scored entry ends at an allowed position: no answer
    assert len(SequenceMatcher().search(10)[0]) == 0  # nothing pushed: nothing to rank
    for bad in ({'length': 0}, {'v_min': 2, 'v_max': 1}, {'max_gap_s': 0}, {'score_norm': 'mean'}):
        with pytest.raises(SequenceError):
            SequenceMatcher(bad)
    with pytest.raises(LLNError, match='2 positions but 1 scores'):
        seq.push(1, [1, 2], [0.5])


def test_keyframe_map_cleared_or_rewritten_empties_the_window():
    ks = KeyframeSequence({'length': 5})
    ks.set_map([1, 2, 3])
    ks.update(0, {1: 0.5, 99: 0.9})  # 99 is not in the map: ignored
    assert len(ks.matcher) == 1 and ks.matcher.ring[0][1].tolist() == [0]
    ks.set_map([1, 2, 3, 4])  # appended (mapping mode): the window stays
    assert len(ks.matcher) == 1
    ks.set_map([])
    assert len(ks.matcher) == 0
    reason, out = ks.update(1, {})
    assert reason is None and out == []


def test_contrast_enhance_matches_its_definition():
    d = np.random.default_rng(0).uniform(0, 1, (4, 30))
    got = contrast_enhance(d, 3)
    for q in range(4):
        for r in range(30):
            w = d[q, max(0, r - 3) : r + 4]
            assert got[q, r] == pytest.approx((d[q, r] - w.mean()) / w.std(), rel=1e-6)


def test_sad_front_end_on_nordland():
    """Real frames: patch normalisation removes the winter/summer brightness change; the same place
    is closer than a place 200 frames away."""
    root = shared_data('nordland_trimmed')
    names = sorted((root / 'summer').iterdir())[2600:2603]
    summer = [cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in names]
    winter = [cv2.imread(str(root / 'winter' / p.name), cv2.IMREAD_GRAYSCALE) for p in names]
    far = [cv2.imread(str(sorted((root / 'summer').iterdir())[2800]), cv2.IMREAD_GRAYSCALE)]
    size = sad_size((summer[0].shape[1], summer[0].shape[0]))
    assert size == (32, 16)
    ref = sad_descriptors(summer + far, size)
    brighter = sad_descriptors([np.clip(im.astype(int) + 40, 0, 255).astype(np.uint8) for im in summer], size)
    assert ref.shape == (4, 512)
    patches = ref[0].reshape(2, 8, 4, 8)
    np.testing.assert_allclose(patches.mean(axis=(1, 3)), 0, atol=1e-5)
    assert sad_difference(brighter[:1], ref[:1])[0, 0] < 0.1  # a brightness offset barely matters
    d = sad_difference(sad_descriptors(winter, size), ref)
    assert d.shape == (3, 4) and np.all(d[:, :3].min(axis=1) < d[:, 3])


def run_cli(*args):
    return main([str(a) for a in args])


def test_eval_peers_and_sequence_rows_on_rtabmap_loop(tmp_path, capsys):
    """sad, seqslam and X+seq rows in one lln-eval run on the real loop sequence."""
    root = shared_data('rtabmap_loop')
    out = tmp_path / 'out'

    def lln_eval(spec, out, timing_queries):
        return run_cli(
            *('--dataset', spec, '--out', out, '--methods', 'holistic,lln,sad,seqslam', '--sequence', 5),
            *('--sequence-prefilter-k', 100),  # more than the map holds (84 frames)
            *('--cache', tmp_path / 'cache', '--timing-images', 1, '--timing-queries', timing_queries),
            *('--timing-repeats', 1, '--no-plots', '--quiet'),
        )

    rc = lln_eval(f'loop:{root},{root / "samples_GT.bmp"}', out, 2)
    assert rc == 0, capsys.readouterr().err
    results = json.loads((out / 'results.json').read_text())
    rows = results['datasets']['rtabmap_loop']['methods']
    assert list(rows) == ['holistic', 'lln', 'sad', 'seqslam', 'holistic+seq', 'lln+seq']
    assert results['parameters']['seqslam']['length'] == 5 and results['parameters']['sequence'] == 5
    for row, m in rows.items():
        assert 0.0 <= m['p_at_100r'] <= 1.0 and m['extract_ms'] > 0, (row, m)
    assert rows['lln+seq']['sequence_ms_per_query'] > 0
    assert rows['lln+seq']['match_ms_per_pair'] == rows['lln']['match_ms_per_pair']
    # the sequence search reranks sequence_prefilter_k (100 > the map) candidates: every allowed frame
    assert results['parameters']['sequence_prefilter_k'] == 100 != retrieval.default_conf['sequence_prefilter_k']
    assert rows['lln+seq']['sequence_candidates'] == 84
    md = (out / 'results.md').read_text()
    assert '| lln+seq |' in md and '| seqslam |' in md
    # the same frames declared not a sequence: no X+seq rows, no seqslam, and a note saying why
    rc = lln_eval(f'loop:{root},{root / "samples_GT.bmp"},sequence=0', tmp_path / 'flat', 1)
    assert rc == 0, capsys.readouterr().err
    entry = json.loads((tmp_path / 'flat' / 'results.json').read_text())['datasets']['rtabmap_loop']
    assert list(entry['methods']) == ['holistic', 'lln', 'sad'] and entry['sequence'] is False
    assert entry['notes'] == [
        '--sequence 5 rows and seqslam skipped: the dataset is not a sequence (its files are not ordered '
        'along one route; add sequence=1 to the spec if they are)'
    ]
    assert entry['methods']['lln'] == {**rows['lln'], **{k: entry['methods']['lln'][k] for k in TIMED}}
    assert 'Note: --sequence 5 rows and seqslam skipped' in (tmp_path / 'flat' / 'results.md').read_text()


TIMED = ('extract_ms', 'match_ms_per_pair')


@pytest.mark.parametrize(
    'flag, values, sequence_moves',
    [('--sequence-carry', (0, 5), True), ('--sequence-acquire-k', (0, 20), False)],
)
def test_eval_sequence_options_move_only_the_sequence_rows(tmp_path, capsys, flag, values, sequence_moves):
    """lln-eval's X+seq options on rtabmap_loop with 3 first-stage candidates: --sequence-carry also scores
    the carried ends' next frames (the matcher's sequence_carry), so the lln+seq row changes;
    --sequence-acquire-k reranks more for the first L - 1 queries (the matcher's sequence_acquire_k; a
    loop's first queries have nothing to revisit, so it may change nothing here). The single-frame row
    never changes, results.json echoes the setting, a negative value is refused."""
    root = shared_data('rtabmap_loop')
    key, rows = flag[2:].replace('-', '_'), {}
    for value in values:
        out = tmp_path / f'{key}{value}'
        rc = run_cli(
            *('--dataset', f'loop:{root},{root / "samples_GT.bmp"}', '--out', out, '--methods', 'lln'),
            *('--sequence', 5, '--prefilter-k', 3, '--sequence-prefilter-k', 3, flag, value),
            *('--cache', tmp_path / 'cache', '--timing-images', 1, '--timing-queries', 1, '--timing-repeats', 1),
            *('--no-plots', '--quiet'),
        )
        assert rc == 0, capsys.readouterr().err
        results = json.loads((out / 'results.json').read_text())
        assert results['parameters'][key] == value
        rows[value] = {
            r: {k: v for k, v in m.items() if 'ms' not in k}
            for r, m in results['datasets']['rtabmap_loop']['methods'].items()
        }
    off, on = (rows[v] for v in values)
    assert off['lln'] == on['lln']
    if sequence_moves:
        assert off['lln+seq'] != on['lln+seq'], rows
    capsys.readouterr()
    assert run_cli('--dataset', 'x', '--out', tmp_path / 'bad', flag, -1) == 2
    assert f'{flag} must be at least 0' in capsys.readouterr().err


def test_acquiring_takes_the_wider_ranking_while_the_window_fills():
    """Offline sequence_acquire_k: the first n queries rank K' candidates, the rest K, padded to K'."""
    base = (np.array([[0, 1], [2, 3], [4, 5]]), np.array([[3, 2], [3, 2], [3, 2]], np.float32))
    wide = (np.array([[9, 0, 1], [8, 2, 3], [7, 4, 5]]), np.array([[5, 3, 2]] * 3, np.float32))
    ranked, scores = acquiring(base, wide, 2)
    assert ranked.tolist() == [[9, 0, 1], [8, 2, 3], [4, 5, -1]]
    assert scores.tolist() == [[5, 3, 2], [5, 3, 2], [3, 2, -np.inf]]
    assert acquiring(base, wide, 0)[0].tolist() == [[0, 1, -1], [2, 3, -1], [4, 5, -1]]


def test_sequence_candidates_are_the_single_frame_first_stage_extended(extractor):
    """rank_all_at: one first stage and one rerank serve the single-frame row (its first K) and the
    sequence row (the first K_seq); each equals rank_all with that K, on rtabmap_loop's real frames."""
    from lln_ros.core.landmarks import stack_landmarks
    from lln_ros.core.retrieval import candidates_k, rank_all, rank_all_at
    from lln_ros.io import datasets
    from lln_ros.io.image import load_image

    root = shared_data('rtabmap_loop')
    ds = datasets.parse_spec(f'loop:{root},{root / "samples_GT.bmp"}')
    sets = extractor.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    batch = stack_landmarks(sets)
    for prefilter in ('landmarks', 'holistic'):
        (r5, s5), (r30, s30) = rank_all_at(sets, batch, (5, 30), ds.candidates, prefilter=prefilter)
        for k, (r, s) in ((5, (r5, s5)), (30, (r30, s30))):
            want_r, want_s = rank_all(sets, batch, k, ds.candidates, prefilter=prefilter)
            assert np.array_equal(r, want_r) and np.allclose(s, want_s, equal_nan=True), (prefilter, k)
        # the single-frame top 5 is among the sequence's 30, every row: a prefix of one first stage
        assert all(set(a[a >= 0]) <= set(b[b >= 0]) for a, b in zip(r5, r30))
        assert (r30 >= 0).sum() > (r5 >= 0).sum()
    assert candidates_k(100, 500, False) == 100 and candidates_k(100, 500, True) == 500
    assert candidates_k(600, 500, True) == 600 and candidates_k(0, 500, True) == 0
    assert candidates_k(100, 0, True) == 0
    with pytest.raises(ValueError, match='sequence_prefilter_k'):
        candidates_k(100, -1, True)


def test_eval_sequence_longer_than_the_map_is_one_line(tmp_path, capsys):
    root = shared_data('rtabmap_loop')
    rc = run_cli(
        '--dataset',
        f'loop:{root},{root / "samples_GT.bmp"}',
        '--out',
        tmp_path / 'out',
        '--methods',
        'sad',
        '--sequence',
        85,
        '--cache',
        tmp_path / 'cache',
        '--no-plots',
        '--quiet',
    )
    err = capsys.readouterr().err
    assert rc == 2 and 'sequence length 85 is longer than its map (84 references)' in err
    rc = run_cli(
        '--dataset',
        f'loop:{root},{root / "samples_GT.bmp"}',
        '--out',
        tmp_path / 'out',
        '--sequence',
        -1,
        '--no-plots',
        '--quiet',
    )
    assert rc == 2 and '--sequence must be 0' in capsys.readouterr().err


def test_candidates_codec_carries_sequence_score_even_with_zero_rows():
    from lln_ros.ros import msgs

    rows = [
        {
            'keyframe_id': 7,
            'score': 3.5,
            'holistic_score': 0.8,
            'stamp_sec': 1,
            'stamp_nanosec': 2,
            'sequence_score': 2.25,
        }
    ]
    table = msgs.cloud_to_candidates(msgs.candidates_to_cloud(rows, None, ('sequence_score',)))
    assert table['sequence_score'].tolist() == [2.25] and table['keyframe_id'].tolist() == [7]
    empty = msgs.cloud_to_candidates(msgs.candidates_to_cloud([], None, ('sequence_score',)))
    assert len(empty) == 0 and empty.dtype.names == table.dtype.names
    assert msgs.candidates_to_cloud([], None, ('sequence_score',)).point_step == 24
