"""Holistic prefilter + landmark rerank, on real images: photo crops (self-contained) and the
rtabmap_loop revisits (with ../shared/data)."""

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.core.extractor import Extractor
from lln_ros.core.landmarks import stack_landmarks
from lln_ros.core.retrieval import LandmarkDatabase, rank_all
from lln_ros.core.similarity import match_batch
from lln_ros.errors import DescriptorError
from lln_ros.io.image import load_image


def crops(photo):
    """Eight overlapping 384x288 views of one photograph, stepping 32 px down."""
    return [photo[y : y + 288, 0:384] for y in range(0, 256, 32)]


def test_each_view_retrieves_itself_first(extractor, photo):
    views = crops(photo)
    sets = extractor.extract_batch(views)
    db = LandmarkDatabase({'prefilter_k': 5})
    db.add(sets)
    for i, s in enumerate(sets):
        cands = db.retrieve(s)
        assert len(cands) == 5 and cands[0].index == i
        assert [c.score for c in cands] == sorted((c.score for c in cands), reverse=True)
        assert cands[0].offset == (0, 0) and len(cands[0].pairs['weight']) == len(s)
        # the neighbour view one step (one cell) away matches with offset (0, -1) or (0, 1)
        nb = [c for c in cands if abs(c.index - i) == 1]
        assert nb and all(c.offset in ((0, 1), (0, -1)) for c in nb)
    every = db.retrieve(sets[2], prefilter_k=0)  # exhaustive: every view, by S
    assert sorted(c.index for c in every) == list(range(len(sets))) and every[0].index == 2
    batch = stack_landmarks(sets)
    ranked, scores = rank_all([sets[2]], batch, prefilter_k=0)
    assert ranked.shape == (1, len(sets)) and ranked[0, 0] == 2
    np.testing.assert_allclose(np.sort(scores[0]), np.sort(match_batch(sets[2], batch).scores), rtol=1e-6)
    hol = db.retrieve(sets[3], rerank_local=False, prefilter='holistic')
    assert hol[0].index == 3 and hol[0].score == pytest.approx(1.0, abs=1e-5) and hol[0].pairs == {}


def test_database_refuses_other_models_and_bad_queries(extractor, photo):
    db = LandmarkDatabase()
    assert db.retrieve(extractor(photo)) == []
    db.add([extractor(photo)])
    other = Extractor({'backbone': {'layer': 'stage7'}, 'num_threads': 2})(photo)
    with pytest.raises(DescriptorError, match='stage7'):
        db.add([other])
    with pytest.raises(DescriptorError, match='the map holds'):
        db.retrieve(other)
    bad = extractor(photo)
    bad.global_descriptor[:] = np.nan
    with pytest.raises(DescriptorError, match='NaN'):
        db.retrieve(bad)


def test_rtabmap_revisits_score_higher_than_non_revisits(extractor):
    """Every frame of rows 40-83 against every frame at least 10 older: true revisits (from
    samples_GT.bmp) must score higher than non-revisits on average, and rank above them."""
    root = shared_data('rtabmap_loop')
    gt = cv2.imread(str(root / 'samples_GT.bmp'), cv2.IMREAD_GRAYSCALE) > 0
    sets = extractor.extract_batch([load_image(str(root / f'{i + 1}.jpg')) for i in range(84)])
    batch = stack_landmarks(sets)
    pos, neg, row_auc = [], [], []
    for r in range(40, 84):
        older = np.arange(0, r - 9)
        scores = match_batch(sets[r], batch).scores[older]
        true = gt[r, older]
        assert true.any(), f'row {r} should hold a revisit'
        pos += list(scores[true])
        neg += list(scores[~true])
        # fraction of (revisit, non-revisit) pairs ranked the right way in this row
        row_auc.append((scores[true][:, None] > scores[~true][None, :]).mean())
    assert np.mean(pos) > 1.5 * np.mean(neg), (np.mean(pos), np.mean(neg))
    assert np.mean(row_auc) > 0.7, np.mean(row_auc)
