"""Spatially weighted cross matching, checked against a plain-loop reference of the paper's
definition, on synthetic sets with known structure and on real image pairs with known shifts."""

import numpy as np
import pytest

from lln_ros.core.landmark_index import center
from lln_ros.core.landmarks import LandmarkSet, l2_normalize, stack_landmarks
from lln_ros.core.similarity import (
    center_sets,
    match_batch,
    match_pair,
    match_sets,
    offset_mode,
    offset_weights,
    pair_offset_mode,
)
from lln_ros.errors import DescriptorError


def make_set(desc, cells, grid=(9, 12), space='test/x/8'):
    desc = l2_normalize(np.asarray(desc, np.float32))
    cells = np.asarray(cells, np.int32)
    cell = np.array([32.0, 32.0], np.float32)
    return LandmarkSet(
        global_descriptor=l2_normalize(desc.max(0)),
        descriptors=desc,
        cells=cells,
        centers=(cells + 0.5) * cell,
        scores=np.linspace(1, 0, len(desc), dtype=np.float32),
        cell_size=cell,
        image_size=np.array([384, 288], np.float32),
        grid=grid,
        descriptor_space=space,
    )


def reference_similarity(a, b, scale=1.0):
    """The paper's S written as loops, independently of the vectorised code."""
    sims = a.descriptors @ b.descriptors.T
    pairs = []
    for i in range(len(a)):
        j = int(np.argmax(sims[i]))
        if int(np.argmax(sims[:, j])) == i:
            pairs.append((i, j, sims[i, j], tuple(a.cells[i] - b.cells[j])))
    if not pairs:
        return 0.0, (0, 0)
    counts = {}
    for _, _, s, d in pairs:
        c, t = counts.get(d, (0, 0.0))
        counts[d] = (c + 1, t + max(s, 0))
    mode = max(counts, key=lambda d: (counts[d][0], counts[d][1]))
    total = sum(s * np.exp(-0.5 * ((d[0] - mode[0]) ** 2 + (d[1] - mode[1]) ** 2) / scale**2) for _, _, s, d in pairs)
    return total, mode


def random_set(rng, n=50, d=8, grid=(9, 12)):
    flat = rng.choice(grid[0] * grid[1], n, replace=False)
    return make_set(rng.normal(size=(n, d)), np.stack([flat % grid[1], flat // grid[1]], 1), grid)


def test_self_match_every_landmark_offset_zero():
    rng = np.random.default_rng(0)
    a = random_set(rng)
    r = match_pair(a, a, center=False)  # the paper's S (the default fuses a whitened S in)
    assert (r.match[0] == np.arange(50)).all()
    assert tuple(r.offsets[0]) == (0, 0)
    np.testing.assert_allclose(r.weight[0], 1.0)
    assert r.scores[0] == pytest.approx(50.0, abs=1e-4)


def test_known_shift_recovered():
    rng = np.random.default_rng(1)
    a = random_set(rng, n=30, grid=(9, 12))
    shifted = a.cells + np.array([3, 2])  # the same features 3 cells right and 2 lower, larger image
    b = make_set(a.descriptors + 0.05 * rng.normal(size=a.descriptors.shape), shifted, grid=(11, 15))
    r = match_pair(a, b)
    assert tuple(r.offsets[0]) == (-3, -2)
    assert (r.match[0] >= 0).sum() == 30


@pytest.mark.parametrize('seed', range(5))
@pytest.mark.parametrize('scale', [0.5, 1.0, 2.0])
def test_matches_reference_definition(seed, scale):
    rng = np.random.default_rng(seed)
    a = random_set(rng, n=20, d=4)
    for _ in range(4):
        b = random_set(rng, n=25, d=4)
        got = match_pair(a, b, scale, center=False)
        want, mode = reference_similarity(a, b, scale)
        assert got.scores[0] == pytest.approx(want, rel=1e-5, abs=1e-6)
        assert tuple(got.offsets[0]) == mode


def test_batched_equals_single_pairs_with_padding():
    rng = np.random.default_rng(2)
    q = random_set(rng, n=40)
    cands = [random_set(rng, n=n) for n in (50, 12, 108 - 8, 40, 1)]
    cands[3] = make_set(q.descriptors + 0.1 * rng.normal(size=q.descriptors.shape), q.cells + 1, grid=(10, 13))
    batch = match_batch(q, stack_landmarks(cands))
    for k, c in enumerate(cands):
        single = match_pair(q, c)
        assert batch.scores[k] == pytest.approx(single.scores[0], rel=1e-6)
        np.testing.assert_array_equal(batch.match[k], single.match[0])
        np.testing.assert_array_equal(batch.offsets[k], single.offsets[0])
    assert np.argmax(batch.scores) == 3


def test_similarity_center_ignores_what_every_landmark_of_an_image_shares():
    """Query: 12 places under a strong condition every landmark of the image shares. Candidate 0:
    the same places under another condition; candidate 1: other places under the query's. Raw S
    (the paper's, the default) prefers candidate 1, S on centred sets candidate 0; centred, a set
    is what landmark_index.center makes of it (one landmark stays as it is), padded or in a list."""
    rng = np.random.default_rng(7)
    d, n = 64, 12
    places, others = l2_normalize(rng.standard_normal((n, d))), l2_normalize(rng.standard_normal((n, d)))
    winter, summer = 2.0 * l2_normalize(rng.standard_normal(d)), 2.0 * l2_normalize(rng.standard_normal(d))
    cells = np.stack([np.arange(n) % 4, np.arange(n) // 4], axis=1)
    query = make_set(places + winter + 0.05 * rng.standard_normal((n, d)), cells)
    cands = [make_set(places + summer, cells), make_set(others + winter, cells)]
    assert np.argmax(match_sets(query, cands, center=True).scores) == 0
    padded = stack_landmarks(cands + [make_set(places[:1], cells[:1])])
    out = center_sets(padded.descriptors, padded.valid)
    assert out.dtype == np.float32  # float64 made every S on centred sets 7x slower
    np.testing.assert_allclose(out[0], center(cands[0].descriptors), atol=1e-6)
    np.testing.assert_allclose(out[2, :1], padded.descriptors[2, :1])
    np.testing.assert_array_equal(out[2, 1:], padded.descriptors[2, 1:])  # padding untouched
    batch = match_batch(query, padded, center=True).scores
    np.testing.assert_allclose(batch[:2], match_sets(query, cands, center=True).scores, rtol=1e-5)


def test_similarity_whiten_is_s_on_centred_then_whitened_sets(monkeypatch):
    """center='whiten': S on each set centred, then x -> W x renormalised with the descriptor space's
    shipped W: the same S as plain S on sets transformed so beforehand. The query differs from its
    place along a 'condition' direction u that another place shares; a W that shrinks u widens the
    true place's lead over centring alone. A space with no whitening is centred only."""
    from lln_ros.core import whitening

    rng = np.random.default_rng(8)
    d, n = 64, 12
    places, others = l2_normalize(rng.standard_normal((n, d))), l2_normalize(rng.standard_normal((n, d)))
    u = np.zeros(d, np.float32)
    u[5] = 1.0
    cells = np.stack([np.arange(n) % 4, np.arange(n) // 4], axis=1)
    shift = 3.0 * rng.choice([-1.0, 1.0], (n, 1)) * u  # per landmark: centring does not remove it
    query = make_set(places + shift, cells, space='test/w/64')
    cands = [make_set(places, cells, space='test/w/64'), make_set(others + shift, cells, space='test/w/64')]
    w = np.eye(d, dtype=np.float32)
    w[5, 5] = 0.05
    monkeypatch.setitem(whitening._SHIPPED, ('test/w/64', 'similarity'), w)
    white = match_sets(query, cands, center='whiten').scores

    def transformed(s):
        x = center(s.descriptors) @ w.T
        return make_set(x, s.cells, space='test/x/64')

    plain = match_sets(transformed(query), [transformed(c) for c in cands], center=False).scores
    np.testing.assert_allclose(white, plain, rtol=1e-5, atol=1e-6)
    assert np.argmax(white) == 0
    assert white[0] - white[1] > np.ptp(match_sets(query, cands, center=True).scores)
    monkeypatch.setitem(whitening._SHIPPED, ('test/w/64', 'similarity'), None)
    np.testing.assert_allclose(
        match_sets(query, cands, center='whiten').scores, match_sets(query, cands, center=True).scores
    )


def test_pairs_and_weights():
    rng = np.random.default_rng(3)
    a = random_set(rng, n=10)
    cells = a.cells.copy()
    cells[:7] -= [1, 0]  # seven landmarks agree on offset (1, 0)
    cells[7:] -= [0, 3]  # three are displaced by (0, 3): down-weighted by exp(-(1+9)/2)
    cells = np.clip(cells, 0, [11, 8])
    b = make_set(a.descriptors, cells)
    r = match_pair(a, b, center=False)
    p = r.pairs(0)
    assert tuple(r.offsets[0]) == (1, 0)
    w = dict(zip(p['query_index'], p['weight']))
    assert all(w[i] == pytest.approx(1.0) for i in range(7) if tuple(a.cells[i] - cells[i]) == (1, 0))
    assert min(w.values()) < 0.05
    assert r.scores[0] == pytest.approx(float((p['weight'] * p['similarity']).sum()), rel=1e-6)


def test_offset_mode_ties_and_empty():
    offsets = np.array([[[1, 0], [1, 0], [2, 2], [2, 2], [5, 5]]])
    matched = np.ones((1, 5), bool)
    sims = np.array([[0.5, 0.5, 0.9, 0.9, 1.0]], np.float32)
    assert tuple(offset_mode(offsets, matched, sims)[0]) == (2, 2)  # tie on count, larger cosine sum
    assert tuple(offset_mode(offsets, np.zeros((1, 5), bool), sims)[0]) == (0, 0)
    w = offset_weights(np.array([[[0, 0], [1, 0], [1, 1]]]), np.array([[0, 0]]), 1.0)
    np.testing.assert_allclose(w[0], [1, np.exp(-0.5), np.exp(-1)], rtol=1e-6)
    with pytest.raises(ValueError):
        offset_weights(offsets, np.zeros((1, 2), int), 0.0)


def test_similarity_fuse_is_raw_plus_weighted_whitened_with_raw_pairs(monkeypatch):
    """center='fuse': S = S(raw) + fusion_weight * S(whitened); the pairs, offsets and weights are raw S's."""
    from lln_ros.core import similarity, whitening

    rng = np.random.default_rng(9)
    d, n = 64, 12
    cells = np.stack([np.arange(n) % 4, np.arange(n) // 4], axis=1)
    query = make_set(l2_normalize(rng.standard_normal((n, d))), cells, space='test/f/64')
    cands = [
        make_set(l2_normalize(rng.standard_normal((n, d))), np.roll(cells, k, 0), space='test/f/64') for k in range(3)
    ]
    w = np.eye(d, dtype=np.float32)
    w[:8] *= 0.1
    monkeypatch.setitem(whitening._SHIPPED, ('test/f/64', 'similarity'), w)
    raw, white = match_sets(query, cands, center=False), match_sets(query, cands, center='whiten')
    for weight in (2.0, 0.5):
        monkeypatch.setitem(similarity.default_conf, 'fusion_weight', weight)
        fused = match_sets(query, cands, center='fuse')
        np.testing.assert_allclose(fused.scores, raw.scores + weight * white.scores, rtol=1e-5)
        for field in ('offsets', 'match', 'similarity', 'weight'):
            np.testing.assert_array_equal(getattr(fused, field), getattr(raw, field))


def test_pair_offset_mode_is_offset_mode_on_a_pair_list():
    """The first stage's pair-list mode (pair_offset_mode, a sort of the pairs) picks the bin the
    dense table picks, ties included, on random small grids where ties are common."""
    rng = np.random.default_rng(7)
    for _ in range(300):
        k, n_a = int(rng.integers(1, 6)), int(rng.integers(1, 12))
        offsets = rng.integers(-2, 3, (k, n_a, 2))
        matched = rng.random((k, n_a)) < 0.6
        sims = rng.choice(np.array([0.25, 0.5, 0.75], np.float32), (k, n_a))  # equal sums happen
        rows = np.broadcast_to(np.arange(k)[:, None], (k, n_a))[matched]
        np.testing.assert_array_equal(
            pair_offset_mode(rows, offsets[matched], sims[matched], k, n_a), offset_mode(offsets, matched, sims)
        )


def test_bad_descriptors():
    rng = np.random.default_rng(4)
    a = random_set(rng, d=8)
    b = random_set(rng, d=16)
    with pytest.raises(DescriptorError, match='size mismatch'):
        match_pair(a, b)
    c = random_set(rng)
    c.descriptors[3, 2] = np.nan
    with pytest.raises(DescriptorError, match='NaN'):
        match_pair(a, c)
    d = random_set(rng)
    d.global_descriptor[0] = np.inf
    with pytest.raises(DescriptorError, match='NaN or inf'):
        match_pair(d, a)
    e = make_set(a.descriptors, a.cells, space='other/y/8')
    with pytest.raises(DescriptorError, match='different models'):
        match_pair(a, e)
    with pytest.raises(DescriptorError, match='different models'):
        stack_landmarks([a, e])
    f = random_set(rng)
    f.cells[0] = [40, 0]
    with pytest.raises(DescriptorError, match='outside'):
        match_pair(a, f)


def test_real_image_against_itself_and_a_shifted_copy(extractor, photo):
    view = photo[100:388, 0:384]  # 384x288: 32 px cells, the paper's grid
    a = extractor(view)
    r = match_pair(a, a)
    assert (r.match[0] == np.arange(len(a))).all() and tuple(r.offsets[0]) == (0, 0)
    # the same scene with the camera moved: content 64 px (2 cells) left and 32 px (1 cell) up
    moved = extractor(photo[132:420, 64:448])
    r = match_pair(a, moved)
    assert tuple(r.offsets[0]) == (2, 1)
    assert (r.match[0] >= 0).sum() >= 10
    other = extractor(np.ascontiguousarray(photo[100:388, 0:384][::-1, ::-1]))
    assert match_pair(a, other).scores[0] < r.scores[0]
