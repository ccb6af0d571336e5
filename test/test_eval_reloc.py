"""lln-eval --reloc: relocalization on the real rtabmap_loop sequence, and its option checks."""

import json

import pytest

from conftest import shared_data
from lln_ros.cli.eval import main


@pytest.fixture(scope='module', autouse=True)
def one_torch_thread(extractor):
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def test_reloc_on_rtabmap_loop(tmp_path, capsys):
    root = shared_data('rtabmap_loop')
    out = tmp_path / 'out'
    rc = main(
        [
            '--dataset',
            f'loop:{root},{root / "samples_GT.bmp"}',
            '--out',
            str(out),
            '--methods',
            'lln',
            '--cache',
            str(tmp_path / 'cache'),
            '--no-plots',
            '--quiet',
            '--timing-images',
            '1',
            '--timing-queries',
            '2',
            '--reloc',
            '--reloc-queries',
            '12',
        ]
    )
    assert rc == 0, capsys.readouterr().err
    entry = json.loads((out / 'results.json').read_text())['datasets']['rtabmap_loop']
    r = entry['reloc']
    assert r['queries'] == 12 and r['top'] == 5 and r['min_inliers'] == 30 and r['row'] == 'lln'
    assert r['true_match_in_top'] >= 0.8 and r['keypoints_median'] > 100
    for name in ('regions', 'all'):
        m = r[name]
        assert 0 <= m['success_rate'] <= 1 and m['ms_per_query'] > 0
        # a true revisit shares far more geometrically consistent keypoints than a wrong place
        assert m['mean_inliers_true'] > 2 * m['mean_inliers_false']
    # indoor loop, same lighting: both pipelines relocalize most revisits (measured 0.82 / 0.86 on all 44)
    assert r['all']['success_rate'] >= 0.6 and r['regions']['success_rate'] >= 0.5
    # fewer candidate pairs to test: the region-constrained pipeline produces fewer putative matches
    assert r['regions']['matches_per_pair'] < r['all']['matches_per_pair']
    md = (out / 'results.md').read_text()
    assert '| mLLN (matched regions) |' in md and '| all keypoints |' in md


def test_reloc_needs_lln(tmp_path, capsys):
    root = shared_data('rtabmap_loop')
    rc = main(
        [
            '--dataset',
            f'loop:{root},{root / "samples_GT.bmp"}',
            '--out',
            str(tmp_path),
            '--methods',
            'holistic',
            '--reloc',
        ]
    )
    assert rc == 2 and 'add lln to --methods' in capsys.readouterr().err
