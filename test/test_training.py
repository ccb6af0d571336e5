"""LLN head training: data sources, mining, determinism, resume, and the checkpoint it ships."""

import pickle

import cv2
import numpy as np
import pytest
import torch

from lln_ros.core import training, training_pairs
from lln_ros.core.extractor import Extractor
from lln_ros.core.lln import LLNHead, load_checkpoint
from lln_ros.errors import DatasetError
from lln_ros.io import datasets


@pytest.fixture(scope='module')
def traverses(tmp_path_factory, photo):
    """Two 'traverses' of 10 places: views of the photograph, the second shifted and darker."""
    root = tmp_path_factory.mktemp('traverses')
    for name, dy, gain in (('ref', 0, 1.0), ('query', 8, 0.7)):
        (root / name).mkdir()
        for i in range(10):
            y = 20 + i * 30 + dy
            view = (photo[y : y + 96, 100:228] * gain).astype(np.uint8)
            cv2.imwrite(str(root / name / f'{i}.png'), cv2.cvtColor(view, cv2.COLOR_RGB2BGR))
    return root


def small_extractor():
    return Extractor({'input_height': 96, 'num_threads': 2})


def conf(**kw):
    return {
        'epochs': 2,
        'lr': 1e-3,
        'tuples_per_epoch': 0,
        'train_size': 96,
        'batch_size': 4,
        'neg_margin': 1,
        'head': {'channels': 8},
        **kw,
    }


def test_pairs_from_dataset_excludes_frames_beside_a_match(traverses):
    ds = datasets.aligned(traverses / 'ref', traverses / 'query', tol=0)
    pairs = training_pairs.pairs_from_dataset(ds, neg_margin=2)
    assert pairs.positive[4].tolist() == [i == 4 for i in range(10)]
    assert pairs.negative[4].tolist() == [i not in (2, 3, 4, 5, 6) for i in range(10)]
    assert not (pairs.positive & pairs.negative).any()


def test_places_and_sfm_layouts(tmp_path, photo):
    for place in ('a', 'b', 'c'):
        (tmp_path / 'places' / place).mkdir(parents=True)
        for k in range(2):
            cv2.imwrite(str(tmp_path / 'places' / place / f'{k}.jpg'), photo[k * 10 : k * 10 + 64, :64])
    p = training_pairs.pairs_from_places(tmp_path / 'places')
    assert len(p.query_paths) == 6 and p.positive.sum() == 6 and not p.positive.diagonal().any()
    assert p.negative[0].sum() == 4
    # Retrieval-SfM-120k: pickle {'train': {cids, cluster, qidxs, pidxs}}, images under ims/ by cid
    cids = [f'{k:08x}abcdef{k}' for k in range(4)]
    for k, cid in enumerate(cids):
        path = training_pairs.sfm_image_path(tmp_path / 'ims', cid)
        path.parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(path) + '.png', photo[k * 20 : k * 20 + 64, :64])
        (path.parent / (path.name + '.png')).rename(path)
    with open(tmp_path / 'db.pkl', 'wb') as f:
        pickle.dump({'train': {'cids': cids, 'cluster': [0, 0, 1, 1], 'qidxs': [0, 2], 'pidxs': [1, 3]}}, f)
    s = training_pairs.pairs_from_sfm(tmp_path / 'db.pkl', tmp_path / 'ims')
    assert s.positive.tolist() == [[False, True, False, False], [False, False, False, True]]
    assert s.negative.tolist() == [[False, False, True, True], [True, True, False, False]]
    both = training_pairs.combine([p, s])
    assert both.positive.shape == (8, 10) and both.positive.sum() == 8
    with pytest.raises(DatasetError, match='not a Retrieval-SfM-120k pickle'):
        (tmp_path / 'bad.pkl').write_bytes(pickle.dumps({'val': {}}))
        training_pairs.pairs_from_sfm(tmp_path / 'bad.pkl', tmp_path / 'ims')
    with pytest.raises(DatasetError, match='SfM images missing'):
        training_pairs.pairs_from_sfm(tmp_path / 'db.pkl', tmp_path / 'elsewhere')


def test_loss_and_embedding():
    head = LLNHead(16, {'channels': 4})
    feats = torch.randn(3, 16, 3, 4)
    f = training.embed(head, feats)
    assert f.shape == (3, 16) and torch.allclose(f.norm(dim=1), torch.ones(3), atol=1e-5)
    q = torch.tensor([[1.0, 0.0]])
    assert training.triplet_loss(q, q, torch.tensor([[[0.0, 1.0]]]), 0.3).item() == 0.0  # well separated
    loss = training.triplet_loss(q, torch.tensor([[0.0, 1.0]]), torch.tensor([[[1.0, 0.0], [0.0, 1.0]]]), 0.3)
    assert loss.item() == pytest.approx((2**0.5 + 0.3) + 0.3, rel=1e-5)


def rerank_trainer(traverses, tmp_path):
    ds = datasets.aligned(traverses / 'ref', traverses / 'query', tol=0)
    t = training.Trainer(
        small_extractor(),
        training_pairs.pairs_from_dataset(ds, neg_margin=1),
        ds,
        conf(val_prefilter_k=5, val_top_n=6),
        cache_dir=str(tmp_path / 'cache'),
        out_dir=str(tmp_path),
    )
    t.load_features()
    t.prepare_rerank()
    return t


def test_match_tables_reproduce_the_similarity_of_all_cells(traverses, tmp_path):
    """The rerank objective's fixed tables hold exactly the paper's S (method `all`): summed over
    query cells they give match_batch's score for every candidate."""
    from lln_ros.core.landmarks import stack_landmarks
    from lln_ros.core.similarity import match_batch

    t = rerank_trainer(traverses, tmp_path)
    ex = small_extractor()
    ex.conf = {**ex.conf, 'method': 'all'}
    q, refs = t.fq[3].numpy(), t.fr.numpy()
    d, h, w = q.shape

    def local(f):
        return f.reshape(d, h * w).T / np.linalg.norm(f.reshape(d, h * w).T, axis=1, keepdims=True)

    cells = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 2)
    partner, value = training.match_tables(local(q), np.stack([local(f) for f in refs]), cells)
    assert partner.shape == value.shape == (10, h * w)
    want = match_batch(
        ex.from_features(q, (128, 96)),
        stack_landmarks([ex.from_features(f, (128, 96)) for f in refs]),
        center=False,  # the paper's S (the default fuses a whitened S in)
    ).scores
    np.testing.assert_allclose(value.sum(1), want, rtol=2e-3)
    assert value.sum(1).argmax() == 3  # the query's own place wins


def test_rerank_scores_use_each_querys_own_candidates(traverses, tmp_path):
    t = rerank_trainer(traverses, tmp_path)
    rows = np.array([4, 1, 7])
    cols = np.array([[0, 1, 2], [2, 0, -1], [1, 3, 0]])
    with torch.no_grad():
        got = t.soft_scores(rows, cols).numpy()
        n, temp = 6, 1.0
        for b, (row, cs) in enumerate(zip(rows, cols)):
            for j, c in enumerate(cs):
                if c < 0:
                    continue
                ref = t.rr_cand[row, c]
                a_q = training.soft_selection(t.head.logits(t.fq[t.queries[row]][None].float()).flatten(1), n, temp)
                a_c = training.soft_selection(t.head.logits(t.fr[ref][None].float()).flatten(1), n, temp)
                p = torch.from_numpy(t.rr_partner[row, c].astype(np.int64))[None, None]
                v = torch.from_numpy(t.rr_value[row, c])[None, None]
                want = training.soft_similarity(a_q, a_c[:, None], p, v, n)[0, 0].item()
                # (batched and single convolutions differ in the last bits)
                assert got[b, j] == pytest.approx(want, rel=1e-4), (row, c)
    # positives first in every candidate list
    for row in range(len(t.queries)):
        q = t.queries[row]
        assert t.pairs.positive[q, t.rr_cand[row, : t.rr_npos[row]]].all()
        assert not t.pairs.positive[q, t.rr_cand[row, t.rr_npos[row] :][t.rr_cand[row, t.rr_npos[row] :] >= 0]].any()


def test_rerank_loss_prefers_positives():
    scores = torch.tensor([[0.9, 0.1, 0.2], [0.1, 0.9, 0.0]])
    n_pos, valid = torch.tensor([1, 1]), torch.ones(2, 3, dtype=torch.bool)
    good = training.rerank_loss(scores, n_pos, valid, 0.05).item()
    assert good < training.rerank_loss(scores.flip(1), n_pos, valid, 0.05).item()
    # padding never counts: masking a candidate out equals leaving it away
    valid[0, 2] = False
    masked = training.rerank_loss(scores[:1], n_pos[:1], valid[:1], 0.05)
    assert masked.item() == pytest.approx(training.rerank_loss(scores[:1, :2], n_pos[:1], valid[:1, :2], 0.05).item())


@pytest.mark.parametrize('objective', ['rerank', 'triplet'])
def test_training_is_deterministic_resumable_and_ships_metadata(traverses, tmp_path, objective):
    ds = datasets.aligned(traverses / 'ref', traverses / 'query', tol=0)
    pairs = training_pairs.pairs_from_dataset(ds, neg_margin=1)

    def run(out, epochs, resume=True):
        t = training.Trainer(
            small_extractor(),
            pairs,
            ds,
            conf(epochs=epochs, objective=objective),
            cache_dir=str(tmp_path / 'cache'),
            out_dir=str(out),
            meta={'command': 'test'},
        )
        return t.fit(resume=resume), t

    # the feature cache is warmed first: features computed in this process and the same features
    # read back can drive the head through different oneDNN kernels (last-bit differences)
    run(tmp_path / 'warm', 1)
    full, t_full = run(tmp_path / 'a', 2)
    assert [h['epoch'] for h in full['history']] == [0, 1, 2]
    assert all(np.isfinite(h['loss']) for h in full['history'][1:])
    again, t_again = run(tmp_path / 'b', 2)
    for k, v in t_full.head.state_dict().items():
        assert torch.equal(v, t_again.head.state_dict()[k]), f'not deterministic: {k}'
    # interrupted after epoch 1, resumed: the same head as an uninterrupted run
    run(tmp_path / 'c', 1)
    resumed, t_resumed = run(tmp_path / 'c', 2)
    assert [h['epoch'] for h in resumed['history']] == [0, 1, 2]
    for k, v in t_full.head.state_dict().items():
        assert torch.equal(v, t_resumed.head.state_dict()[k]), f'resume differs: {k}'
    head, meta = load_checkpoint(str(tmp_path / 'a' / 'best.pt'), 'efficientnet_lite0', 'stage6', 192)
    assert meta['command'] == 'test' and meta['train_data'] == pairs.name
    # the images it saw, so lln-eval can say which datasets are held out for it
    keys = datasets.image_keys([*ds.query_paths, *ds.ref_paths])
    assert meta['seen_images'] == {'train': keys, 'val': keys} and len(keys) == len(ds.query_paths) + len(ds.ref_paths)
    # best.pt is the first epoch with the best validation score, the untrained head (epoch 0) included
    scores = [h['val_p_at_100r'] for h in full['history']]
    assert meta['epoch'] == scores.index(max(scores)) and meta['trained'] == (meta['epoch'] > 0)
    assert 0 <= meta['val_p_at_100r'] <= 1
    with pytest.raises(DatasetError, match='another training configuration'):
        training.Trainer(
            small_extractor(),
            pairs,
            ds,
            conf(epochs=3, lr=0.5, objective=objective),
            cache_dir=str(tmp_path / 'cache'),
            out_dir=str(tmp_path / 'c'),
        ).fit()


def test_cli_rejects_bad_data_before_work(tmp_path, capsys):
    from lln_ros.cli.train import main

    (tmp_path / 'a').mkdir()
    assert main(['--data', f'aligned:{tmp_path / "a"},{tmp_path / "b"}', '--out', str(tmp_path / 'o')]) == 2
    assert 'lln-train: error:' in capsys.readouterr().err and not (tmp_path / 'o').exists()


@pytest.fixture(scope='module')
def square_traverses(tmp_path_factory, photo):
    """Six places as square views (another grid than `traverses`), the second pass brighter."""
    root = tmp_path_factory.mktemp('square')
    for name, dx, gain in (('ref', 0, 1.0), ('query', 6, 1.2)):
        (root / name).mkdir()
        for i in range(6):
            x = 30 + i * 40 + dx
            view = np.clip(photo[150:246, x : x + 96] * gain, 0, 255).astype(np.uint8)
            cv2.imwrite(str(root / name / f'{i}.png'), cv2.cvtColor(view, cv2.COLOR_RGB2BGR))
    return root


@pytest.mark.parametrize('padding', ['zeros', 'replicate'])
def test_padding_keeps_the_logits_of_real_cells(padding):
    """The trainer pads a small map to the batch grid as the head's convs pad past the border (zeros,
    or the last row and column repeated), so a real cell's logit is the one it has on its own."""
    g = torch.Generator().manual_seed(0)
    small, big = torch.randn(12, 3, 2, generator=g).abs(), torch.randn(12, 3, 4, generator=g).abs()
    feats, valid = training.pad_stack([small.numpy(), big.numpy()], mode=padding)
    assert feats.shape == (2, 12, 3, 4) and valid.reshape(2, 3, 4)[0].tolist() == [[True, True, False, False]] * 3
    for prior in (0.0, 0.5):
        head = LLNHead(12, {'channels': 4, 'norm_prior': prior, 'padding': padding})
        with torch.no_grad():
            torch.testing.assert_close(head.logits(feats)[0, :, :2], head.logits(small[None])[0])
    # the other mode would change the real cells next to the padding: the test can tell them apart
    other = training.pad_stack([small.numpy(), big.numpy()], mode='zeros' if padding == 'replicate' else 'replicate')
    head = LLNHead(12, {'channels': 4, 'padding': padding})
    with torch.no_grad():
        assert not torch.allclose(head.logits(other[0])[0, :, :2], head.logits(small[None])[0])


def test_correction_bound_keeps_the_head_within_b_of_act():
    """correction_bound b: however large the learned weights, logit - log|f| stays in [-b, b], so
    the feature norm (ACT) always keeps a say; b = 0 leaves the correction unbounded."""
    feats = torch.randn(2, 16, 5, 7, generator=torch.Generator().manual_seed(2)).abs()
    prior = torch.log(feats.norm(dim=1) + 1e-6)
    for bound, within in ((0.5, True), (0.0, False)):
        head = LLNHead(16, {'channels': 4, 'norm_prior': 1.0, 'correction_bound': bound})
        with torch.no_grad():
            head.fuse.weight.normal_(0, 100.0, generator=torch.Generator().manual_seed(3))
            correction = head.logits(feats) - prior
        assert (correction.abs().max() <= 0.5 + 1e-5) == within
    with pytest.raises(Exception, match='correction_bound'):
        LLNHead(16, {'correction_bound': -1})
    with pytest.raises(Exception, match='padding'):
        LLNHead(16, {'padding': 'reflect'})


def test_lateral_crops_train_as_queries_with_their_originals_labels(traverses, tmp_path):
    """crop_views: every usable query gains crops of its feature map (full height, a window of
    crop_range x its width) that are queries with its positives and negatives."""
    rng = np.random.default_rng(0)
    feats = [np.arange(2 * 3 * 10, dtype=np.float32).reshape(2, 3, 10)] * 3
    crops, origin = training.lateral_crops(feats, np.array([0, 2]), 4, (0.5, 0.8), rng)
    assert origin.tolist() == [0] * 4 + [2] * 4
    for c in crops:
        w = c.shape[2]
        assert c.shape[:2] == (2, 3) and 5 <= w <= 8
        x0 = int(c[0, 0, 0])  # the first row of the map counts 0..9: a crop starts where it was cut
        np.testing.assert_array_equal(c, feats[0][:, :, x0 : x0 + w])
    assert len({int(c[0, 0, 0]) for c in crops}) > 1  # not always the same place
    with pytest.raises(DatasetError, match='crop_range'):
        training.lateral_crops(feats, np.array([0]), 1, (0.0, 0.5), rng)

    ds = datasets.aligned(traverses / 'ref', traverses / 'query', tol=0, name='wide')
    pairs = training_pairs.pairs_from_dataset(ds, 1)
    t = training.Trainer(
        small_extractor(),
        pairs,
        None,
        conf(crop_views=2, crop_range=(0.5, 0.75), head={'channels': 4, 'norm_prior': 1.0}),
        cache_dir=str(tmp_path / 'cache'),
        out_dir=str(tmp_path / 'out'),
    )
    usable = t.queries.copy()
    t.load_features()
    n = len(pairs.query_paths)
    assert len(t.queries) == 3 * len(usable) and t.fq.shape[0] == n + 2 * len(usable)
    crop_rows = t.queries[len(usable) :]
    origin = np.repeat(usable, 2)
    np.testing.assert_array_equal(t.pairs.positive[crop_rows], pairs.positive[origin])
    np.testing.assert_array_equal(t.pairs.negative[crop_rows], pairs.negative[origin])
    full_w = int(t.q_valid[0].reshape(t.fq.shape[2:]).sum(1)[0])
    crop_w = t.q_valid[crop_rows].reshape(-1, *t.fq.shape[2:]).sum(2)[:, 0]
    assert (crop_w < full_w).all() and (crop_w >= 1).all()
    t.prepare_rerank()  # every crop gets match tables against its original's candidates
    assert len(t.rr_npos) == len(t.queries)


def test_norm_prior_starts_at_act():
    """norm_prior > 0: the untrained head ranks cells exactly by feature norm (ACT's selection)."""
    feats = torch.randn(2, 16, 5, 7, generator=torch.Generator().manual_seed(1))
    head = LLNHead(16, {'channels': 4, 'norm_prior': 1.0})
    with torch.no_grad():
        order = head.logits(feats).flatten(1).argsort(1)
    assert torch.equal(order, feats.norm(dim=1).flatten(1).argsort(1))


@pytest.mark.parametrize('objective', ['rerank', 'triplet'])
def test_datasets_of_different_grids_train_together_and_best_is_the_validation_mean(
    traverses, square_traverses, tmp_path, objective
):
    wide = datasets.aligned(traverses / 'ref', traverses / 'query', tol=0, name='wide')  # 4x3 cells
    square = datasets.aligned(square_traverses / 'ref', square_traverses / 'query', tol=0, name='square')  # 3x3
    pairs = training_pairs.combine(
        [training_pairs.pairs_from_dataset(wide, 1), training_pairs.pairs_from_dataset(square, 1)]
    )
    t = training.Trainer(
        small_extractor(),
        pairs,
        [wide, square],
        conf(
            epochs=2,
            objective=objective,
            val_prefilter_k=4,
            val_top_n=6,
            head={'channels': 8, 'norm_prior': 1.0} if objective == 'rerank' else {'channels': 8},
        ),
        cache_dir=str(tmp_path / 'cache'),
        out_dir=str(tmp_path / 'out'),
    )
    result = t.fit()
    assert t.fq.shape[2:] == (3, 4) and t.q_valid[-1].sum() == 9 and t.q_valid[0].all()
    if objective == 'rerank':  # padded cells are never matched
        assert (t.rr_value[:, :, ~t.q_valid[-1]][len(t.queries) - 1] == 0).all()
    hist = result['history']
    assert [h['epoch'] for h in hist] == [0, 1, 2]
    for h in hist:
        assert set(h['val_per_set']) == {wide.name, square.name}
        assert h['val_p_at_100r'] == pytest.approx(np.mean(list(h['val_per_set'].values())))
    best = max(hist, key=lambda h: h['val_p_at_100r'])  # the first of equals: later ones must beat it
    _, meta = load_checkpoint(str(tmp_path / 'out' / 'best.pt'))
    assert meta['epoch'] == best['epoch'] and meta['val_data'] == [wide.name, square.name]
    assert meta['val_p_at_100r'] == pytest.approx(best['val_p_at_100r']) and meta['trained'] == (best['epoch'] > 0)


def test_balance_sets_gives_every_training_set_the_same_share(tmp_path):
    """--balance-sets: a 40-query set and a 5-query set give an epoch the same number of queries
    (the small one's again); without it, every usable query once."""

    def pairs(name, q):  # query i matches ref i; every other ref is a negative
        pos = np.eye(q, q + 2, dtype=bool)
        return training.PairSet(
            name, [f'{name}/q{i}' for i in range(q)], [f'{name}/r{i}' for i in range(q + 2)], pos, ~pos
        )

    both = training_pairs.combine([pairs('big', 40), pairs('small', 5)])
    assert both.source.tolist() == [0] * 40 + [1] * 5

    def chosen(**kw):
        t = training.Trainer(small_extractor(), both, None, conf(**kw), cache_dir=str(tmp_path), out_dir=str(tmp_path))
        return t.choose_queries()

    plain = chosen()
    assert sorted(plain.tolist()) == list(range(45))
    balanced = chosen(balance_sets=True)  # 45 queries: 23 + 23 drawn, one dropped at random
    small = balanced[both.source[balanced] == 1]
    assert len(balanced) == 45 and len(small) in (22, 23) and set(small.tolist()) == set(range(40, 45))
    assert np.bincount(small - 40).min() >= 4  # the small set's queries in turns, not 22 draws of one
    big = balanced[both.source[balanced] == 0]
    assert len(set(big.tolist())) == len(big)  # the big set's without replacement
    ten = chosen(balance_sets=True, tuples_per_epoch=10)
    assert sorted(ten[ten >= 40].tolist()) == list(range(40, 45)) and len(set(ten[ten < 40].tolist())) == 5


def test_lln_train_refuses_a_bound_without_the_norm_prior(tmp_path):
    """--correction-bound bounds the correction to log|f|: without --norm-prior there is none, and
    the flag would be dropped silently; the command says so before any data is read."""
    from lln_ros.cli import train
    from lln_ros.cli.common import UsageError

    args = train.build_parser().parse_args(
        ['--data', 'vprbench:/nonexistent', '--out', str(tmp_path), '--correction-bound', '1']
    )
    with pytest.raises(UsageError, match='needs --norm-prior'):
        train.run(args)
