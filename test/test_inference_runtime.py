"""The two inference runtimes (lln_ros.core.runtime): same landmarks on real frames, the exported graph's
cache, the fallback, model_info, and maps shared across runtimes."""

import json
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.core import runtime
from lln_ros.core.extractor import Extractor
from lln_ros.errors import ModelError
from lln_ros.io.image import load_image
from lln_ros.mapstore import MapStore

pytestmark = pytest.mark.skipif(not runtime.onnxruntime_available(), reason='onnxruntime is not installed')

NORDLAND_STEP = 20  # every 20th frame of the summer traverse: 179 frames along the whole line
FLOAT16_STEP = 2.0**-12  # one float16 step in [0.25, 0.5)


@pytest.fixture(scope='module')
def pair():
    """(torch extractor, onnxruntime extractor), same model, one thread each."""
    t = Extractor({'runtime': 'torch', 'num_threads': 1})
    o = Extractor({'runtime': 'onnxruntime', 'num_threads': 1})
    assert (t.model_info['runtime'], o.model_info['runtime']) == ('torch', 'onnxruntime')
    return t, o


def same_cells(x, y, rel: float = 1e-5) -> bool:
    """The same cells in the same order, except that cells whose scores tie to float32 precision
    (relative `rel`) may come in either order: the two runtimes round differently in the last bits."""
    if len(x.cells) != len(y.cells):
        return False
    where = {tuple(c): k for k, c in enumerate(x.cells.tolist())}
    for k, c in enumerate(y.cells.tolist()):
        j = where.get(tuple(c))
        if j is None or abs(x.scores[j] - x.scores[k]) > rel * abs(x.scores[k]):
            return False
    return True


def compare(t: Extractor, o: Extractor, images: list) -> dict:
    a, b = t.extract_batch(images), o.extract_batch(images)
    same = [same_cells(x, y) for x, y in zip(a, b)]
    # descriptors are compared row by row, so only on frames without a swapped tie
    both = [(x, y) for x, y in zip(a, b) if np.array_equal(x.cells, y.cells)]
    return {
        'frames': len(images),
        'cells_identical': int(sum(same)),
        'order_identical': len(both),
        # descriptors are float16-exact unit vectors (the map stores them so). Equal to float16
        # precision: no element differs by more than one float16 step at the size of a unit vector's
        # largest entries (2**-12 in [0.25, 0.5)); a feature whose float16 rounding flips between the
        # runtimes moves every element of its normalised vector by a little, so small elements can be
        # several of their own (smaller) steps apart
        'desc_max_diff': max(float(np.abs(x.descriptors - y.descriptors).max()) for x, y in both),
        'desc_elements_identical': float(
            np.mean(np.concatenate([(x.descriptors == y.descriptors).ravel() for x, y in both]))
        ),
        'desc_min_cosine': min(
            float(
                np.min(
                    np.sum(x.descriptors * y.descriptors, 1)
                    / np.linalg.norm(x.descriptors, axis=1)
                    / np.linalg.norm(y.descriptors, axis=1)
                )
            )
            for x, y in both
        ),
        'global_max_diff': max(float(np.abs(x.global_descriptor - y.global_descriptor).max()) for x, y in both),
        'grids': {(x.grid, y.grid) for x, y in zip(a, b)},
    }


def test_same_cells_allows_only_swapped_ties():
    def lm(cells, scores):
        return SimpleNamespace(cells=np.array(cells), scores=np.array(scores, np.float32))

    a = lm([[0, 0], [1, 0], [2, 0]], [3.0, 2.0, 2.0])
    assert same_cells(a, lm([[0, 0], [2, 0], [1, 0]], [3.0, 2.0, 2.0]))  # the tie in either order
    assert not same_cells(a, lm([[1, 0], [0, 0], [2, 0]], [3.0, 2.0, 2.0]))  # 3.0 and 2.0 swapped
    assert not same_cells(a, lm([[0, 0], [1, 0], [3, 0]], [3.0, 2.0, 2.0]))  # another cell


def rtabmap_frames() -> list:
    root = shared_data('rtabmap_loop')
    return [load_image(str(root / f'{i}.jpg')) for i in range(1, 85)]


def test_same_landmarks_on_rtabmap_loop(pair):
    """All 84 frames (512x384 -> 384x288, a 12x9 grid): the same cells, in the same order up to
    float32 ties, on >= 99% of frames, and descriptors equal to float16 precision."""
    r = compare(*pair, rtabmap_frames())
    print(r)
    assert r['grids'] == {((9, 12), (9, 12))}
    assert r['cells_identical'] >= 0.99 * r['frames'], r
    assert r['desc_max_diff'] <= FLOAT16_STEP and r['desc_min_cosine'] > 1 - 1e-5, r
    assert r['desc_elements_identical'] > 0.95 and r['global_max_diff'] < 1e-3, r


def test_same_landmarks_on_nordland(pair):
    """A Nordland slice (64x32 -> 576x288, an 18x9 grid: another width through the same dynamic graph)."""
    root = shared_data('nordland_trimmed', 'summer')
    paths = sorted(root.glob('*.png'))[::NORDLAND_STEP]
    r = compare(*pair, [load_image(str(p)) for p in paths])
    print(r)
    assert r['frames'] >= 170
    assert r['grids'] == {((9, 18), (9, 18))}
    assert r['cells_identical'] >= 0.99 * r['frames'], r
    assert r['desc_max_diff'] <= FLOAT16_STEP and r['desc_min_cosine'] > 1 - 1e-5, r
    assert r['desc_elements_identical'] > 0.95 and r['global_max_diff'] < 1e-3, r


def test_every_network_size_through_one_graph(pair, photo):
    """The graph keeps height and width dynamic: 384x288, 512x288, 576x288, 288x320 and a tall 160x352
    all give torch's grid and features (the size-dependent padding of EfficientNet is exported right)."""
    t, o = pair
    for w, h in ((384, 288), (512, 288), (576, 288), (288, 320), (160, 352)):
        rgb = cv2.resize(photo, (w, h), interpolation=cv2.INTER_AREA)[None]
        (ft, lt), (fo, lo) = t.network(rgb), o.network(rgb)
        assert ft.shape == fo.shape == (1, 192, h // 32, w // 32), (w, h)
        assert np.abs(ft - fo).max() <= np.spacing(np.abs(ft).max().astype(np.float16)), (w, h)
        assert np.abs(lt - lo).max() < 0.05 * np.abs(lt).max(), (w, h)


def test_ort_folds_every_pad_into_its_convolution(pair, tmp_path):
    """ONNX Runtime's optimised graph of the exported file has no Pad node left: each was fused into
    the next Conv (a Pad left in takes the tensor out of ORT's blocked layout and back, ~1/3 of
    the time per frame; runtime._let_ort_fuse_pads)."""
    import onnx
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
    so.optimized_model_filepath = str(tmp_path / 'optimised.onnx')
    ort.InferenceSession(pair[1].network.path, so, providers=['CPUExecutionProvider'])
    ops = [n.op_type for n in onnx.load(so.optimized_model_filepath).graph.node]
    assert ops.count('Conv') + ops.count('FusedConv') >= 40 and 'Pad' not in ops, sorted(set(ops))


def test_onnx_network_refuses_sizes_it_would_get_wrong(pair):
    with pytest.raises(ModelError, match='multiples of 32'):
        pair[1].network(np.zeros((1, 288, 390, 3), np.uint8))


def test_model_info_names_the_runtime_and_default(pair):
    assert pair[0].model_info['runtime'] == 'torch'
    assert pair[1].model_info['runtime'] == 'onnxruntime'
    # the descriptor space does not depend on the runtime: the map's compatibility key
    assert pair[0].descriptor_space == pair[1].descriptor_space
    from lln_ros.core.extractor import default_conf

    assert default_conf['runtime'] == 'onnxruntime'
    with pytest.raises(ModelError, match='unknown runtime'):
        Extractor({'runtime': 'tensorflow'})


@pytest.mark.parametrize('build,query', [('torch', 'onnxruntime'), ('onnxruntime', 'torch')])
def test_map_built_with_one_runtime_answers_the_other(pair, tmp_path, build, query):
    """A map of rtabmap_loop frames 1-40 made with one runtime; frames 41-84 (the second lap) queried
    with the other give the same top-5 keyframes as queries made with the map's own runtime."""
    by = {'torch': pair[0], 'onnxruntime': pair[1]}
    frames = rtabmap_frames()
    with MapStore.open(tmp_path / 'map.db', model=by[build].model_info) as store:
        store.add_many(by[build].extract_batch(frames[:40]), [(i, 0) for i in range(40)])
        store.use_model(by[query].model_info)  # the other runtime's extractor comes up: accepted
        assert store.model['runtime'] == build
        own = [store.query(s, k=5) for s in by[build].extract_batch(frames[40:])]
        other = [store.query(s, k=5) for s in by[query].extract_batch(frames[40:])]
    ids = [([c.keyframe_id for c in a], [c.keyframe_id for c in b]) for a, b in zip(own, other)]
    print(
        build,
        '->',
        query,
        'same top-1',
        sum(a[0] == b[0] for a, b in ids),
        'same top-5',
        sum(a == b for a, b in ids),
        'of',
        len(ids),
    )
    assert sum(a[0] == b[0] for a, b in ids) >= 0.95 * len(ids), ids
    assert sum(a == b for a, b in ids) >= 0.9 * len(ids), ids
    top1 = [(a[0].score, b[0].score) for a, b in zip(own, other) if a[0].keyframe_id == b[0].keyframe_id]
    assert max(abs(x - y) / abs(x) for x, y in top1) < 0.01, top1


# ------------------------------------------------------------------ the exported graph's cache


def test_export_is_cached_and_keyed_by_the_weights(tmp_path, monkeypatch):
    """First use exports into $LLN_CACHE/onnx; a second extractor reuses the file; another head (the
    untrained Xavier one) or another layer gets its own file."""
    monkeypatch.setenv('LLN_CACHE', str(tmp_path))
    a = Extractor({'runtime': 'onnxruntime'})
    files = sorted((tmp_path / 'onnx').glob('*.onnx'))
    assert len(files) == 1 and a.model_info['runtime'] == 'onnxruntime'
    assert files[0].name.startswith(f'efficientnet_lite0_{a.model_info["layer"]}_')
    mtime = files[0].stat().st_mtime_ns
    Extractor({'runtime': 'onnxruntime'})
    assert files[0].stat().st_mtime_ns == mtime  # not exported again
    b = Extractor({'runtime': 'onnxruntime', 'weights': '', 'backbone': {'layer': 'stage7'}})
    assert b.model_info['runtime'] == 'onnxruntime' and b.model_info['head'] != a.model_info['head']
    assert len(list((tmp_path / 'onnx').glob('*.onnx'))) == 2
    assert not list((tmp_path / 'onnx').glob('*.tmp'))


def test_damaged_cache_file_is_exported_again(tmp_path, monkeypatch, photo):
    monkeypatch.setenv('LLN_CACHE', str(tmp_path))
    good = Extractor({'runtime': 'onnxruntime'})(photo)
    path = next((tmp_path / 'onnx').glob('*.onnx'))
    path.write_bytes(path.read_bytes()[:1000])  # a torn file
    again = Extractor({'runtime': 'onnxruntime'})
    assert again.model_info['runtime'] == 'onnxruntime'
    assert np.array_equal(again(photo).cells, good.cells)


def test_without_onnxruntime_it_says_so_once_and_runs_torch(tmp_path):
    """A Python where `import onnxruntime` fails (as on a machine without it): torch runs, one log line."""
    code = (
        'import logging, sys; sys.modules["onnxruntime"] = None; logging.basicConfig(level=logging.INFO); '
        'from lln_ros.core.extractor import Extractor; e = Extractor(); print("RUNTIME", e.model_info["runtime"])'
    )
    out = subprocess.run(
        [sys.executable, '-c', code],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, 'LLN_CACHE': str(tmp_path)},
    )
    assert out.returncode == 0, out.stderr
    assert 'RUNTIME torch' in out.stdout
    warned = [line for line in out.stderr.splitlines() if 'onnxruntime' in line]
    assert len(warned) == 1 and 'not installed' in warned[0] and 'torch' in warned[0], out.stderr
    assert not (tmp_path / 'onnx').exists()


def test_lln_export_command(tmp_path):
    """`lln-export` (the console script) writes the graph and checks it against torch."""
    exe = Path(sys.executable).parent / 'lln-export'
    out = subprocess.run(
        [str(exe), '--output', str(tmp_path / 'net.onnx'), '--json'],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, 'LLN_CACHE': str(tmp_path / 'cache')},
    )
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)
    assert Path(r['path']) == tmp_path / 'net.onnx' and (tmp_path / 'net.onnx').stat().st_size > 1e6
    assert r['model']['runtime'] == 'onnxruntime' and r['max_feature_diff'] < 0.05
    bad = subprocess.run([str(exe), '--layer', 'stage9'], capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and 'stage9' in bad.stderr and 'Traceback' not in bad.stderr


def test_lln_match_runtime_flag(tmp_path):
    root = shared_data('rtabmap_loop')
    exe = Path(sys.executable).parent / 'lln-match'
    answers = {}
    for rt in ('torch', 'onnxruntime'):
        out = subprocess.run(
            [str(exe), str(root / '5.jpg'), str(root / '50.jpg'), '--runtime', rt, '--json'],
            capture_output=True,
            text=True,
            timeout=600,
        )
        assert out.returncode == 0, out.stderr
        answers[rt] = json.loads(out.stdout)
        assert answers[rt]['model']['runtime'] == rt
    assert answers['torch']['pairs'] == answers['onnxruntime']['pairs']
    assert abs(answers['torch']['similarity'] - answers['onnxruntime']['similarity']) < 1e-3
    bad = subprocess.run(
        [str(exe), str(root / '5.jpg'), str(root / '50.jpg'), '--runtime', 'tf'],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert bad.returncode == 2 and 'unknown runtime' in bad.stderr


# ------------------------------------------------------------------ the node parameter


def test_extractor_node_runtime_parameter(tmp_path):
    """The real node (its console script, own DDS domain): `runtime` picks the runtime, the latched
    model_info says which ran, and both publish the same landmark cells for the same image."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Image, PointCloud2
    from std_msgs.msg import String

    from lln_ros.ros import msgs
    from ros_harness import VENV_BIN, Probe, RosProcess, ros_env

    image = cv2.resize(load_image(str(shared_data('rtabmap_loop', '5.jpg'))), (384, 288))
    env = ros_env(tmp_path, {'LLN_CACHE': os.environ.get('LLN_CACHE', str(runtime.cache_dir()))})
    cells = {}
    for rt in ('torch', 'onnxruntime'):
        proc = RosProcess(
            VENV_BIN / 'extractor',
            ['-p', f'runtime:={rt}', '-p', 'num_threads:=1', '-p', 'reliability:=reliable'],
            env,
            tmp_path / f'{rt}.log',
        )
        try:
            with Probe(env) as probe:
                info, got = [], probe.collect(PointCloud2, 'lln/landmarks')
                probe.node.create_subscription(
                    String,
                    'lln/model_info',
                    lambda m: info.append(json.loads(m.data)),
                    QoSProfile(
                        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
                    ),
                )
                pub = probe.publisher(Image, 'image')
                probe.spin_until(
                    lambda: not proc.alive() or (info and pub.get_subscription_count() > 0), 120, 'extractor up'
                )
                assert proc.alive(), proc.log()
                assert info[0]['runtime'] == rt and info[0]['descriptor_space'] == 'efficientnet_lite0/stage6/192'
                pub.publish(msgs.array_to_image(image, 'rgb8', msgs.make_header(1_000_000_000, 'cam')))
                probe.spin_until(lambda: got, 120, 'landmarks')
                cells[rt] = msgs.cloud_to_landmarks(got[0])
        finally:
            proc.stop()
        assert f', {rt}) from' in proc.log()  # the start-up line names it
    assert same_cells(cells['torch'], cells['onnxruntime'])  # up to float32 ties, as offline


# ------------------------------------------------------------------------------ int8 (onnxruntime-int8)


@pytest.fixture(scope='module')
def int8():
    """(onnxruntime float extractor, onnxruntime-int8 extractor), one thread each."""
    f = Extractor({'runtime': 'onnxruntime', 'num_threads': 1})
    q = Extractor({'runtime': 'onnxruntime-int8', 'num_threads': 1})
    assert q.model_info['runtime'] == 'onnxruntime-int8'
    return f, q


def closeness(f: Extractor, q: Extractor, images: list) -> dict:
    """How close int8 landmarks are to float ones: the share of the float top-n cells int8 also
    selects (per frame), and the cosine between the two descriptors of each shared cell."""
    overlap, cosines = [], []
    for x, y in zip(f.extract_batch(images), q.extract_batch(images)):
        at = {tuple(c): k for k, c in enumerate(y.cells.tolist())}
        both = [(k, at[tuple(c)]) for k, c in enumerate(x.cells.tolist()) if tuple(c) in at]
        overlap.append(len(both) / len(x.cells))
        i, j = np.array(both).T
        cosines.append(np.sum(x.descriptors[i].astype(np.float32) * y.descriptors[j], 1))
    cos = np.concatenate(cosines)
    return {
        'mean_overlap': float(np.mean(overlap)),
        'min_overlap': float(np.min(overlap)),
        'median_cosine': float(np.median(cos)),
        'p05_cosine': float(np.percentile(cos, 5)),
    }


def test_int8_landmarks_are_close_to_float_on_rtabmap_loop(int8):
    """All 84 frames, none of which calibrated the int8 graph (the sample photograph did): int8 picks
    >= 97% of the float graph's 50 cells on average (>= 90% on every frame), and the descriptors of
    the cells both pick point the same way (median cosine >= 0.99, 5% quantile >= 0.97). ONNX Runtime's
    int8 kernels depend on the CPU: the machines before 2026-12-06 (CPU not recorded) passed >= 0.98
    for the mean overlap and the 5% quantile; an EPYC without AVX2 gave 0.979 / min 0.92 / median
    0.991 / 5% quantile 0.976 on 2026-12-06. What this costs in retrieval: docs/benchmarks.md, int8."""
    r = closeness(*int8, rtabmap_frames())
    print(r)
    assert r['mean_overlap'] >= 0.97 and r['min_overlap'] >= 0.9, r
    assert r['median_cosine'] >= 0.99 and r['p05_cosine'] >= 0.97, r


def test_int8_graph_is_cached_beside_the_float_one_and_its_features_apart(tmp_path, monkeypatch, photo):
    """onnxruntime-int8 quantises the exported float graph once into $LLN_CACHE/onnx (a second
    extractor reuses it); a feature cache keeps int8 features in their own folder, so evaluation
    never mixes them with float ones."""
    from lln_ros.io.features import FeatureCache

    monkeypatch.setenv('LLN_CACHE', str(tmp_path))
    a = Extractor({'runtime': 'onnxruntime-int8'})
    files = sorted(p.name for p in (tmp_path / 'onnx').glob('*.onnx'))
    assert len(files) == 2 and files[1] == files[0].replace('.onnx', f'_int8q{runtime.QUANT_VERSION}.onnx')
    int8_file = tmp_path / 'onnx' / files[1]
    mtime = int8_file.stat().st_mtime_ns
    b = Extractor({'runtime': 'onnxruntime-int8'})
    assert int8_file.stat().st_mtime_ns == mtime and b.network.path == str(int8_file)
    assert np.array_equal(a(photo).cells, b(photo).cells)
    assert not list((tmp_path / 'onnx').glob('*.tmp')) and not list((tmp_path / 'onnx').glob('*pre.onnx'))
    float_root = FeatureCache(tmp_path / 'f', Extractor({'runtime': 'onnxruntime'})).root
    assert FeatureCache(tmp_path / 'f', a).root != float_root
