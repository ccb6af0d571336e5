"""Adaptation of the LLN head to a user's own traverse without ground truth (issue 28, part 3).

The robot's own images carry one label for free: their order. Frames a few frames apart show the
same place (positives); frames far apart in time show other places (negatives), as long as the
traverse does not come back to where it was. Frames in between are neither, so a slow robot's
near-duplicates beyond the positive gap are never pushed apart. The result is a PairSet
(training_pairs.py) the existing Trainer fits, starting from the shipped head (start_from) or
from scratch.

Default gaps: positives 1..2 frames apart, negatives 20 or more frames apart. At the 10-frame
subsampling of the shared Nordland copy, 2 frames is about the ground-truth tolerance of its
evaluation (1 frame) plus one; 20 frames is past any view overlap on a train route. A traverse
that revisits places (a loop) makes some negatives wrong: pass a larger neg_gap or use poses.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from ..errors import DatasetError, ModelError
from ..io.datasets import _select, list_images
from .lln import load_checkpoint
from .training_pairs import PairSet

default_conf = {
    'pos_gap': 2,  # frames 1..pos_gap apart are positives
    'neg_gap': 20,  # frames neg_gap or more apart are negatives
}


def sequence_masks(n: int, pos_gap: int, neg_gap: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, n) bool positive and negative masks of n frames in time order (the diagonal is neither)."""
    if not 1 <= pos_gap < neg_gap:
        raise DatasetError(f'sequence pseudo-labels need 1 <= pos_gap < neg_gap, got {pos_gap}, {neg_gap}')
    gap = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    return (gap >= 1) & (gap <= pos_gap), gap >= neg_gap


def pairs_from_sequence(
    folder: str | os.PathLike, frac=None, pos_gap: int | None = None, neg_gap: int | None = None
) -> PairSet:
    """A folder of one traverse's frames (file names sort in time order) -> pseudo-labelled pairs:
    every frame queries every other one. frac (start, end) keeps that part of the traverse."""
    pos_gap = default_conf['pos_gap'] if pos_gap is None else int(pos_gap)
    neg_gap = default_conf['neg_gap'] if neg_gap is None else int(neg_gap)
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f'sequence folder not found: {folder}')
    paths = list_images(folder)
    paths = paths[_select(len(paths), frac)]
    if len(paths) <= neg_gap:
        raise DatasetError(
            f'{folder}: {len(paths)} frames, but negatives need frames at least {neg_gap} apart; '
            'give a longer traverse or a smaller NEG_GAP'
        )
    pos, neg = sequence_masks(len(paths), pos_gap, neg_gap)
    name = f'sequence:{folder.name}' + (f'[{frac[0]:g}:{frac[1]:g}]' if frac else '')
    return PairSet(name, paths, paths, pos, neg)


def parse_sequence_spec(rest: str, frac=None) -> PairSet:
    """'DIR[,POS_GAP,NEG_GAP]' (the part after 'sequence:') -> pairs_from_sequence."""
    folder, *gaps = rest.split(',')
    if len(gaps) not in (0, 2):
        raise DatasetError(f'sequence:DIR[,POS_GAP,NEG_GAP] expected, got sequence:{rest}')
    try:
        gaps = [int(g) for g in gaps]
    except ValueError:
        raise DatasetError(f'sequence: POS_GAP and NEG_GAP are whole frame counts, got {rest!r}') from None
    return pairs_from_sequence(folder, frac, *gaps)


def start_from(trainer, path: str) -> dict:
    """Start trainer's head from the checkpoint at path (fine-tuning) and reset its optimiser.
    The checkpoint must fit the trainer's backbone, layer and head configuration (e.g. the
    head configuration the checkpoint records, as lln-train --init sets it). Returns the checkpoint's
    metadata."""
    bb = trainer.extractor.conf['backbone']
    head, meta = load_checkpoint(path, bb['name'], trainer.extractor.backbone.layer, trainer.head.in_dim)
    want = {k: v for k, v in trainer.head.conf.items() if k != 'seed'}
    have = {k: v for k, v in head.conf.items() if k != 'seed'}
    if want != have:
        raise ModelError(
            f'{path!r} has head configuration {have}, the training is configured for {want} '
            "(fine-tuning needs the checkpoint's head configuration; lln-train --init takes it from the checkpoint)"
        )
    trainer.head.load_state_dict(head.state_dict())
    trainer.optimizer = torch.optim.Adam(trainer.head.parameters(), lr=trainer.conf['lr'])
    trainer.meta['init_from'] = str(path)
    trainer.meta['init_train_data'] = meta.get('train_data')
    return meta
