"""lln-match as a person runs it: the installed console script, real image files."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import pytest

from conftest import shared_data
from lln_ros.core.similarity import default_conf as SIM

LLN_MATCH = str(Path(sys.executable).with_name('lln-match'))


def run(*args):
    return subprocess.run([LLN_MATCH, *map(str, args)], capture_output=True, text=True, timeout=300)


@pytest.fixture(scope='module')
def views(tmp_path_factory, photo):
    d = tmp_path_factory.mktemp('views')
    a, b = d / 'a.png', d / 'b.png'
    cv2.imwrite(str(a), cv2.cvtColor(photo[100:388, 0:384], cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(b), cv2.cvtColor(photo[132:420, 64:448], cv2.COLOR_RGB2BGR))  # moved 2 cells, 1 cell
    return a, b


def test_json_output(views):
    out = run(*views, '--json', '--top-n', '30')
    assert out.returncode == 0, out.stderr
    result = json.loads(out.stdout)  # stdout is exactly one JSON object
    assert result['n'] == 30 and result['offset'] == [2, 1]
    assert 0 < result['pairs'] <= 30 and result['similarity'] > 0
    assert len(result['matches']) == result['pairs']


def test_text_and_plot(views, tmp_path):
    png = tmp_path / 'm.png'
    out = run(*views, '--method', 'all', '--plot', png)
    assert out.returncode == 0, out.stderr
    assert 'similarity S =' in out.stdout and 'offset (dx, dy) = (2, 1)' in out.stdout
    img = cv2.imread(str(png))
    assert img is not None and img.shape[1] > img.shape[0] > 300


def test_bad_input_is_one_clear_line(views, tmp_path):
    out = run(views[0], tmp_path / 'missing.png')
    assert out.returncode == 2 and 'image file not found' in out.stderr and 'Traceback' not in out.stderr
    (tmp_path / 'bad.jpg').write_bytes(b'garbage')
    out = run(views[0], tmp_path / 'bad.jpg', '--json')
    assert out.returncode == 2 and 'cannot decode' in out.stderr and out.stdout == ''
    out = run(views[0], views[1], '--backbone', 'resnet101')
    assert out.returncode == 2 and 'weights_path' in out.stderr


def test_on_shared_images():
    root = shared_data('rtabmap_loop')
    same = json.loads(run(root / '41.jpg', root / '41.jpg', '--json').stdout)
    assert same['pairs'] == same['n'] == 50 and same['offset'] == [0, 0]
    # the default fused S: 50 raw + fusion_weight x 50 whitened (every pair's cosine 1, weight 1)
    assert same['similarity'] == pytest.approx(50.0 * (1 + SIM['fusion_weight']), abs=3e-3)
