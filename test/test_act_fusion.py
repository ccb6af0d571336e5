"""act_fusion: the lln selection's rank fusion with ACT's feature norm (issue 28)."""

import numpy as np
import pytest

from lln_ros.core.extractor import Extractor, fused_logits
from lln_ros.core.landmarks import select_landmarks
from lln_ros.errors import ModelError
from lln_ros.eval.methods import parse_head


def _maps(seed=0, shape=(9, 12)):
    rng = np.random.default_rng(seed)
    # logits on the trained head's scale (thousands), norms on the features' (tens)
    return (rng.normal(8000, 3000, shape)).astype(np.float32), rng.uniform(40, 110, shape).astype(np.float32)


def test_zero_is_the_head_and_one_is_act():
    logits, norms = _maps()
    assert fused_logits(logits, norms, 0.0) is logits
    n = 50
    act = select_landmarks(norms, n, 'act')
    fused = select_landmarks(fused_logits(logits, norms, 1.0), n, 'lln')
    assert set(fused) == set(act)


def test_half_takes_from_both_whatever_the_scales():
    logits, norms = _maps(1)
    n = 30
    head = set(select_landmarks(logits, n, 'lln'))
    act = set(select_landmarks(norms, n, 'act'))
    for scale in (1e-3, 1.0, 1e4):  # rank fusion: the logits' scale does not matter
        half = set(select_landmarks(fused_logits(logits * scale, norms, 0.5), n, 'lln'))
        assert half != head and half != act
        assert head & act <= half  # a cell both rank in their top n ranks in the fused top n
    # a value mix would be the head alone at these scales: ranks are what makes a = 0.5 mean half
    value_mix = set(select_landmarks(0.5 * logits + 0.5 * np.log(norms), n, 'lln'))
    assert value_mix == head


def test_parse_head_settings():
    h = parse_head('mix=shipped@act_fusion=0.5')
    assert (h.label, h.weights, h.select) == ('mix', 'shipped', {'act_fusion': 0.5})
    assert parse_head('plain=shipped').select == {}
    with pytest.raises(ValueError, match='unknown head setting'):
        parse_head('x=shipped@top_n=3')
    with pytest.raises(ValueError, match='not a number'):
        parse_head('x=shipped@act_fusion=half')


@pytest.mark.parametrize('bad', [-0.1, 1.5])
def test_extractor_rejects_out_of_range(bad):
    with pytest.raises(ModelError, match='act_fusion'):
        Extractor({'act_fusion': bad})
