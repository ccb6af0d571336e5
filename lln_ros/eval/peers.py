"""Classic place-recognition peers for lln-eval, computed on the same queries as the other methods.

    sad       single frame: downsampled, patch-normalised grey images compared by mean absolute
              difference (the SeqSLAM front end, Milford and Wyeth ICRA 2012); score = -difference
    seqslam   the same differences, locally contrast-enhanced along the map, then the sequence
              search of lln_ros.core.sequence (length L, velocity range); score = -mean enhanced difference

and `sequence_row`: any method's single-frame ranking turned into a sequence ranking (`X+seq`).
"""

from __future__ import annotations

import time

import cv2
import numpy as np

from ..core.sequence import (
    contrast_enhance,
    dense_to_ranked,
    rank_sequences,
    sad_conf,
    sad_descriptors,
    sad_difference,
    sad_size,
)

PEER_METHODS = ('sad', 'seqslam')


def _grey(path) -> np.ndarray:
    im = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if im is None:
        from ..errors import ImageError

        raise ImageError(f'cannot read image {path}')
    return im


class SadFrontEnd:
    """The SAD descriptors of one dataset's references and queries, computed once for sad and seqslam."""

    def __init__(self, ds, conf: dict | None = None):
        self.conf = {**sad_conf, **(conf or {})}
        ref_grey = [_grey(p) for p in ds.ref_paths]
        self.size = sad_size((ref_grey[0].shape[1], ref_grey[0].shape[0]), self.conf)
        self.refs = sad_descriptors(ref_grey, self.size, self.conf)  # (R, w*h)
        same = [str(p) for p in ds.ref_paths] == [str(p) for p in ds.query_paths]
        self.queries = (
            self.refs if same else sad_descriptors([_grey(p) for p in ds.query_paths], self.size, self.conf)
        )  # (Q, w*h)
        self.difference = sad_difference(self.queries, self.refs)  # (Q, R)

    def extraction_job(self, path):
        """Read, downsample and normalise one image (what a new frame costs)."""
        return lambda: sad_descriptors([_grey(path)], self.size, self.conf)

    def match_job(self, q: int):
        """One query against the whole map (divide by R for a per-pair figure)."""
        return lambda: sad_difference(self.queries[q : q + 1], self.refs)


def peer_row(method: str, front: SadFrontEnd, allowed, k: int, seq_conf: dict):
    """ranked (Q, k), scores (Q, k) of a peer method."""
    if method == 'sad':
        return dense_to_ranked(-front.difference, allowed, k)
    enhanced = -contrast_enhance(front.difference, int(front.conf['enhance_window']))
    full, full_scores = dense_to_ranked(enhanced, allowed)
    # SeqSLAM as published: its contrast enhancement is its normalisation, the line search averages that
    return rank_sequences(full, full_scores, front.refs.shape[0], {**seq_conf, 'score_norm': 'none'}, allowed, k)


def sequence_row(
    ranked: np.ndarray, scores: np.ndarray, n_refs: int, seq_conf: dict, allowed, k: int, carry=0, score_of=None
):
    """(ranked (Q, k), scores (Q, k), ms per query of the sequence search) from a single-frame ranking;
    carry, score_of: rank_sequences' (the matcher's sequence_carry)."""
    t = time.perf_counter()
    out = rank_sequences(ranked, scores, n_refs, seq_conf, allowed, k, carry, score_of)
    return out + ((time.perf_counter() - t) * 1e3 / max(len(ranked), 1),)
