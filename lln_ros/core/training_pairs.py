"""Training data of the LLN head (training.py): a PairSet of query and reference images with boolean
positive / negative masks, made from an evaluation dataset (aligned traverses, VPR-Bench, loop and
pose sequences), place-labelled folders or the Retrieval-SfM-120k pickle, and combinable."""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..io.datasets import list_images


@dataclass
class PairSet:
    """Training pairs. positive / negative (Q, R) bool: ref r is a positive / negative of query q.
    source (Q,) int: which of the combined sets each query comes from (None: one set)."""

    name: str
    query_paths: list
    ref_paths: list
    positive: np.ndarray
    negative: np.ndarray
    source: np.ndarray | None = None

    def usable(self) -> np.ndarray:
        """Queries that can form a tuple: at least one positive and enough negatives."""
        return np.flatnonzero(self.positive.any(1) & (self.negative.sum(1) >= 1))


def pairs_from_dataset(ds, neg_margin: int = 10) -> PairSet:
    """A PairSet from an evaluation Dataset (lln_ros.io.datasets): positives are its ground truth;
    negatives are refs farther than neg_margin refs (in ref order) from every positive, so frames
    just beside a match are neither."""
    gt = np.asarray(ds.gt, bool)
    near = gt.copy()
    for shift in range(1, int(neg_margin) + 1):
        near[:, shift:] |= gt[:, :-shift]
        near[:, :-shift] |= gt[:, shift:]
    negative = ~near & gt.any(1, keepdims=True)
    if getattr(ds, 'candidates', None) is not None:
        negative &= ds.candidates
    return PairSet(ds.name, list(ds.query_paths), list(ds.ref_paths), gt, negative)


def pairs_from_places(root: str | os.PathLike) -> PairSet:
    """DIR/<place>/*.jpg: every image queries every other; same folder = positive, other = negative."""
    root = Path(root)
    if not root.is_dir():
        raise DatasetError(f'place folder not found: {root}')
    paths, labels = [], []
    for label, place in enumerate(sorted(p for p in root.iterdir() if p.is_dir())):
        images = list_images(place)
        paths += images
        labels += [label] * len(images)
    if not paths:
        raise DatasetError(f'no images in place folders under {root} (expected {root}/<place>/*.jpg)')
    labels = np.array(labels)
    same = labels[:, None] == labels[None, :]
    np.fill_diagonal(same, False)
    other = labels[:, None] != labels[None, :]
    return PairSet(f'places:{root.name}', paths, paths, same, other)


def sfm_image_path(ims_root: str | os.PathLike, cid: str) -> Path:
    """cirtorch's layout of Retrieval-SfM-120k images: ims/<cid[-2:]>/<cid[-4:-2]>/<cid[-6:-4]>/<cid>."""
    return Path(ims_root) / cid[-2:] / cid[-4:-2] / cid[-6:-4] / cid


def pairs_from_sfm(pickle_path: str | os.PathLike, ims_root: str | os.PathLike, split: str = 'train') -> PairSet:
    """The Retrieval-SfM-120k pickle the paper trained on: {split: {'cids', 'cluster', 'qidxs',
    'pidxs'}}. Query qidxs[i] has positive pidxs[i]; negatives are images of other clusters."""
    try:
        with open(pickle_path, 'rb') as f:
            db = pickle.load(f)[split]
        cids, cluster = list(db['cids']), np.asarray(db['cluster'])
        qidxs, pidxs = np.asarray(db['qidxs'], np.int64), np.asarray(db['pidxs'], np.int64)
    except FileNotFoundError:
        raise DatasetError(f'SfM pickle not found: {pickle_path}') from None
    except (KeyError, TypeError, pickle.UnpicklingError, EOFError) as e:
        raise DatasetError(f'{pickle_path} is not a Retrieval-SfM-120k pickle with split {split!r}: {e}') from e
    if (
        len(cluster) != len(cids)
        or len(qidxs) != len(pidxs)
        or (len(qidxs) and max(qidxs.max(), pidxs.max()) >= len(cids))
    ):
        raise DatasetError(
            f'{pickle_path}: inconsistent {split} lists (cids {len(cids)}, cluster {len(cluster)}, '
            f'qidxs {len(qidxs)}, pidxs {len(pidxs)})'
        )
    paths = [sfm_image_path(ims_root, c) for c in cids]
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(f'{len(missing)} SfM images missing under {ims_root}, e.g. {missing[0]}')
    positive = np.zeros((len(qidxs), len(cids)), bool)
    positive[np.arange(len(qidxs)), pidxs] = True
    negative = cluster[qidxs][:, None] != cluster[None, :]
    return PairSet(f'sfm:{split}', [paths[i] for i in qidxs], paths, positive, negative)


def combine(sets: list[PairSet]) -> PairSet:
    """Several PairSets as one: block diagonal (no pairs across sources)."""
    if len(sets) == 1:
        return sets[0]
    q = sum(len(s.query_paths) for s in sets)
    r = sum(len(s.ref_paths) for s in sets)
    pos, neg = np.zeros((q, r), bool), np.zeros((q, r), bool)
    source = np.zeros(q, int)
    qo = ro = 0
    for i, s in enumerate(sets):
        source[qo : qo + len(s.query_paths)] = i
        pos[qo : qo + len(s.query_paths), ro : ro + len(s.ref_paths)] = s.positive
        neg[qo : qo + len(s.query_paths), ro : ro + len(s.ref_paths)] = s.negative
        qo, ro = qo + len(s.query_paths), ro + len(s.ref_paths)
    return PairSet(
        '+'.join(s.name for s in sets),
        sum((s.query_paths for s in sets), []),
        sum((s.ref_paths for s in sets), []),
        pos,
        neg,
        source,
    )
