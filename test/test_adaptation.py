"""Adaptation without ground truth (lln_ros/core/adaptation.py, lln-train --data sequence:DIR --init):
pseudo-labels from frame order on a real traverse, fine-tuning from the shipped head."""

import numpy as np
import pytest
import torch

from conftest import shared_data
from lln_ros.core import adaptation
from lln_ros.errors import DatasetError, ModelError


def test_sequence_masks_follow_the_gaps():
    pos, neg = adaptation.sequence_masks(8, 2, 5)
    assert pos[3].nonzero()[0].tolist() == [1, 2, 4, 5]
    assert neg[3].nonzero()[0].tolist() == []  # in 8 frames none is 5 or more from frame 3
    assert neg[0].nonzero()[0].tolist() == [5, 6, 7]
    assert not (pos & neg).any() and not pos.diagonal().any() and not neg.diagonal().any()
    assert (pos == pos.T).all() and (neg == neg.T).all()
    with pytest.raises(DatasetError, match='pos_gap < neg_gap'):
        adaptation.sequence_masks(8, 3, 3)


def test_pairs_from_a_real_traverse_folder():
    summer = shared_data('nordland_trimmed', 'summer')
    pairs = adaptation.parse_sequence_spec(f'{summer},1,10', (0.7, 0.72))
    n = len(pairs.query_paths)
    assert 60 <= n <= 80 and pairs.ref_paths is pairs.query_paths
    assert pairs.name == 'sequence:summer[0.7:0.72]'
    names = [p.name for p in pairs.query_paths]
    assert names == sorted(names)  # time order is file order
    assert pairs.positive.sum(1).max() == 2 and pairs.usable().size == n
    with pytest.raises(DatasetError, match='negatives need frames at least 500 apart'):
        adaptation.pairs_from_sequence(summer, (0.7, 0.72), 2, 500)
    with pytest.raises(DatasetError, match='POS_GAP and NEG_GAP'):
        adaptation.parse_sequence_spec(f'{summer},a,b')
    with pytest.raises(DatasetError, match='not found'):
        adaptation.pairs_from_sequence(summer / 'nope')


def test_lln_train_fine_tunes_the_shipped_head_on_a_traverse(tmp_path):
    from lln_ros.cli import train
    from lln_ros.core.extractor import shipped_weights
    from lln_ros.core.lln import load_checkpoint

    summer = shared_data('nordland_trimmed', 'summer')
    out = tmp_path / 'adapt'
    args = train.build_parser().parse_args(
        [
            '--data', f'sequence:{summer},1,10', '--range', '0.7:0.71', '--init', 'shipped',
            '--epochs', '1', '--tuples-per-epoch', '20', '--threads', '2', '--cache', str(tmp_path / 'cache'),
            '--out', str(out),
        ]
    )  # fmt: skip
    train.run(args)
    head, meta = load_checkpoint(str(out / 'best.pt'))
    shipped, shipped_meta = load_checkpoint(shipped_weights('efficientnet_lite0', 'stage6'))
    assert meta['init_from'] == shipped_weights('efficientnet_lite0', 'stage6')
    assert meta['init_train_data'] == shipped_meta['train_data'] and meta['trained'] and meta['epoch'] == 1
    assert meta['train_data'] == 'sequence:summer[0.7:0.71]'
    # fine-tuned: moved from the shipped weights, but not far in one small epoch
    a, b = head.state_dict(), shipped.state_dict()
    moved = [float((a[k] - b[k]).abs().max()) for k in a]
    assert max(moved) > 0
    x = torch.randn(1, head.in_dim, 6, 8)
    corr = np.corrcoef(head.logits(x).detach().flatten(), shipped.logits(x).detach().flatten())[0, 1]
    assert corr > 0.5


def test_init_needs_the_head_configuration_of_the_checkpoint(tmp_path, extractor):
    from lln_ros.core import training
    from lln_ros.core.extractor import shipped_weights

    summer = shared_data('nordland_trimmed', 'summer')
    pairs = adaptation.pairs_from_sequence(summer, (0.7, 0.71), 1, 10)
    ckpt = shipped_weights('efficientnet_lite0', 'stage6')
    plain = training.Trainer(extractor, pairs, None, {}, cache_dir=str(tmp_path / 'c'), out_dir=str(tmp_path / 'o'))
    with pytest.raises(ModelError, match="checkpoint's head configuration"):
        adaptation.start_from(plain, ckpt)
    from lln_ros.core.lln import load_checkpoint

    recorded = {k: v for k, v in load_checkpoint(ckpt)[0].conf.items() if k != 'seed'}
    prior = training.Trainer(
        extractor,
        pairs,
        None,
        {'head': recorded},
        cache_dir=str(tmp_path / 'c'),
        out_dir=str(tmp_path / 'o'),
    )
    adaptation.start_from(prior, ckpt)
    shipped, _ = load_checkpoint(ckpt)
    for k, v in shipped.state_dict().items():
        assert torch.equal(prior.head.state_dict()[k], v)
