"""Online = offline sequence figures on the same bag: rtabmap_loop as an MCAP bag played into the
colcon-installed extractor and matcher (mapping mode, sequence_length 10), scored like lln-eval's
`lln+seq` row on the same frames; with the paper's holistic top-30 prefilter and with every keyframe
scored (prefilter_k 0)."""

import numpy as np
import pytest
from test_e2e_rtabmap import GAP, play_rtabmap

from conftest import shared_data
from lln_ros.core import metrics
from lln_ros.eval import evaluate_dataset
from lln_ros.io import datasets

LENGTH = 10


@pytest.fixture(scope='module', params=[30, 0], ids=['prefilter30', 'exhaustive'])
def online(request, colcon_install, tmp_path_factory):
    run = play_rtabmap(
        colcon_install,
        tmp_path_factory.mktemp('e2e_seq'),
        ['-p', 'k:=10', '-p', f'sequence_length:={LENGTH}', '-p', f'prefilter_k:={request.param}'],
    )
    return run['stamps'], run['answers'], request.param


def test_online_sequence_figures_equal_lln_eval(online, extractor, tmp_path):
    root = shared_data('rtabmap_loop')
    stamps, got, prefilter_k = online
    ds = datasets.parse_spec(f'loop:{root},{root / "samples_GT.bmp"}')
    assert len(got) == len(ds.query_paths) and [t for t, _ in got] == stamps
    index_of = {s: i for i, s in enumerate(stamps)}
    ranked = np.full((len(got), 10), -1, np.int64)
    scores = np.full((len(got), 10), -np.inf, np.float32)
    for q, (_, cands) in enumerate(got):
        refs = [index_of[int(s) * 10**9 + int(n)] for s, n in zip(cands['stamp_sec'], cands['stamp_nanosec'])]
        assert all(r <= q - GAP for r in refs), (q, refs)
        ranked[q, : len(refs)], scores[q, : len(refs)] = refs, cands['sequence_score']
    on = metrics.summary(ranked, scores[:, 0], ds.gt)
    run = evaluate_dataset(
        ds,
        extractor,
        {
            'methods': ['lln'],
            'sequence': LENGTH,
            'plots': False,
            'prefilter_k': prefilter_k,
            'cache_dir': str(tmp_path / 'cache'),
            'progress': False,
            'timing_images': 1,
            'timing_queries': 1,
            'timing_repeats': 1,
        },
    )
    off = run.entry['methods']['lln+seq']
    print(
        f'\nrtabmap_loop lln+seq (prefilter_k {prefilter_k}) online: P@100%R {on["p_at_100r"]:.3f} '
        f'R@100%P {on["r_at_100p"]:.3f}; '
        f'offline (lln-eval): P@100%R {off["p_at_100r"]:.3f} R@100%P {off["r_at_100p"]:.3f}'
    )
    # the same search on the same frames; the single-frame scores differ only by the node's JPEG
    # decode path and float16 map storage, so allow one query of 44 either way
    assert abs(on['p_at_100r'] - off['p_at_100r']) <= 1 / 44 + 1e-9
    assert abs(on['r_at_100p'] - off['r_at_100p']) <= 2 / 44 + 1e-9
