"""lln-reloc on real image files, as a subprocess (the module entry point: a new console script
only exists after the package is reinstalled, and the module is what it runs)."""

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from conftest import shared_data


def run(*args):
    return subprocess.run(
        [sys.executable, '-m', 'lln_ros.cli.reloc', *map(str, args)], capture_output=True, text=True, timeout=300
    )


@pytest.fixture(scope='module')
def views(tmp_path_factory, photo):
    d = tmp_path_factory.mktemp('views')
    a, b = d / 'a.png', d / 'b.png'
    cv2.imwrite(str(a), cv2.cvtColor(photo[100:388, 0:384], cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(b), cv2.cvtColor(photo[132:420, 64:448], cv2.COLOR_RGB2BGR))
    return a, b


def test_json_has_both_pipelines(views):
    out = run(*views, '--json')
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    for key in ('inliers_regions', 'inliers_all', 'ms_regions', 'ms_all'):
        assert key in r
    assert r['verified_regions'] and r['verified_all']
    assert 15 <= r['inliers_regions'] <= r['regions']['matches']
    assert r['inliers_all'] >= 15 and r['ms_regions'] > 0 and r['ms_all'] > 0
    assert r['region_pairs'] > 0 and r['regions']['R'] is None  # no intrinsics: F only


def test_text_plot_and_intrinsics(tmp_path):
    root = shared_data('rtabmap_loop')
    (tmp_path / 'cam.yaml').write_text('camera_matrix: {rows: 3, cols: 3, data: [440, 0, 256, 0, 440, 192, 0, 0, 1]}\n')
    png = tmp_path / 'r.png'
    out = run(root / '42.jpg', root / '41.jpg', '--plot', png, '--intrinsics', tmp_path / 'cam.yaml')
    assert out.returncode == 0, out.stderr
    assert 'regions (mLLN)' in out.stdout and 'all keypoints' in out.stdout and 'verified' in out.stdout
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 500
    out = run(root / '42.jpg', root / '41.jpg', '--json', '--intrinsics', tmp_path / 'cam.yaml')
    r = json.loads(out.stdout)
    assert r['all']['model'] == 'E' and len(r['all']['R']) == 3


def test_bad_input_is_one_clear_line(views, tmp_path):
    out = run(views[0], tmp_path / 'missing.png')
    assert out.returncode == 2 and 'image file not found' in out.stderr and 'Traceback' not in out.stderr
    out = run(*views, '--intrinsics', tmp_path / 'missing.yaml')
    assert out.returncode == 2 and 'cannot read camera intrinsics' in out.stderr
    blank = tmp_path / 'blank.png'
    cv2.imwrite(str(blank), np.full((288, 384), 128, np.uint8))
    out = run(views[0], blank, '--json')
    r = json.loads(out.stdout)
    assert out.returncode == 0 and not r['verified_all'] and 'no keypoints' in r['all']['reason']
