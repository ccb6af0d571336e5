"""lln-demo, the README's first command: a tiny aligned dataset (crops of a real photograph) through
the real nodes (two extractors and the matcher as separate processes over DDS), online figures equal
to the offline evaluator's; outputs; bad input; clean-up on Ctrl-C; the default dataset."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import SHARED_DATA, shared_data
from lln_ros.cli import demo

REPO = Path(__file__).resolve().parents[1]
DEMO = [sys.executable, '-m', 'lln_ros.cli.demo']
FRAMES = 10
RUN_TIMEOUT = 600  # a loaded 2-core CI machine starts three torch/rclpy processes slowly


def run_demo(*args, timeout=RUN_TIMEOUT, cwd=REPO):
    # the shared data folder as scripts/main_job.sh names it (installed code never guesses a path)
    env = {**os.environ, 'LLN_DATA': os.environ.get('LLN_DATA', str(SHARED_DATA))}
    return subprocess.run([*DEMO, *args], capture_output=True, text=True, timeout=timeout, cwd=cwd, env=env)


@pytest.fixture(scope='module')
def tiny_dataset(tmp_path_factory) -> str:
    """Two 'traverses' of one photograph: map frames are 10 crops; query frames are the same places
    shifted by a few pixels, darker, with sensor noise (same index = same place, tolerance 0)."""
    import matplotlib.cbook as cbook

    root = tmp_path_factory.mktemp('tiny')
    (root / 'map').mkdir()
    (root / 'query').mkdir()
    with cbook.get_sample_data('grace_hopper.jpg') as f:
        bgr = cv2.imread(f.name)  # 600 x 512
    rng = np.random.default_rng(0)
    h, w = 120, 256
    places = [(y, x) for y in (0, 120, 240, 360, 470) for x in (0, 250)]
    assert len(places) == FRAMES
    for i, (y, x) in enumerate(places):
        yq, xq = min(y + 9, bgr.shape[0] - h), min(x + 14, bgr.shape[1] - w)
        query = bgr[yq : yq + h, xq : xq + w].astype(np.float32) * 0.75 + 10 + rng.normal(0, 4, (h, w, 3))
        cv2.imwrite(str(root / 'map' / f'{i:03d}.png'), bgr[y : y + h, x : x + w])
        cv2.imwrite(str(root / 'query' / f'{i:03d}.png'), np.clip(query, 0, 255).astype(np.uint8))
    return f'aligned:{root / "map"},{root / "query"},0'


@pytest.fixture(scope='module')
def tiny_run(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp('demo') / 'out'
    done = run_demo('--dataset', tiny_dataset, '--out', str(out))
    assert done.returncode == 0, f'{done.stdout}\n{done.stderr}'
    return {
        'out': out,
        'stdout': done.stdout,
        'stderr': done.stderr,
        'results': json.loads((out / 'results_online.json').read_text()),
    }


# ------------------------------------------------------------------------------------ the real run


def test_online_equals_offline(tiny_run):
    r = tiny_run['results']
    online, offline, cmp = r['online'], r['offline'], r['comparison']
    for key, _ in demo.METRICS:
        assert online[key] == offline[key], (key, online, offline)
    assert cmp['agree'] and cmp['same_top1'] == FRAMES and cmp['lost_queries'] == 0, cmp
    assert cmp['score_rel_diff_max'] < 1e-3, cmp  # the same S up to float16 rounding
    assert online['answered'] == FRAMES
    assert online['p_at_100r'] >= 0.5, online  # the photo's places are recognisable
    assert 'online and offline AGREE on every metric' in tiny_run['stdout']
    for key in ('P@100%R', 'R@100%P', 'AUC-PR', 'R@1', 'R@5', 'R@10'):
        assert key in tiny_run['stdout']


def test_no_frame_lost_and_counters_agree(tiny_run):
    tr = tiny_run['results']['transport']
    for phase in ('map', 'query'):
        t = tr[phase]
        # the first frame of a phase is sent again when it went out before the extractor's writer had
        # matched the matcher's reader (the handshake); nothing else is ever sent twice
        assert t['resent'] < demo.HANDSHAKE_TRIES, t
        assert t['extractor_received'] == t['extractor_published'] == FRAMES + t['resent'], t
        assert t['frames'] == t['landmarks_seen'] == FRAMES, t
        assert t['extractor_dropped'] == 0 and t['lost'] == 0, t
    m = tr['map']
    assert m['keyframes_stored'] == m['keyframes_in_map_file'] == tr['keyframes_in_map_at_end'] == FRAMES
    assert tr['map']['duplicate_keyframes'] == 0
    assert tr['query']['answered'] == tr['query']['queries_answered_counter'] == FRAMES
    assert tr['map']['bad_keyframe'] == tr['query']['bad_query'] == 0
    assert tr['unknown_keyframe_stamps'] == tr['unknown_query_stamps'] == 0
    dup = tr['duplicates']  # only a handshake's second copy of a first frame can be seen twice
    assert dup['keyframes'] <= tr['map']['resent'] and dup['query'] <= tr['query']['resent'], tr
    assert dup['candidates'] <= tr['query']['resent'], tr


def test_nodes_ran_as_ros2_run_would_and_stopped_cleanly(tiny_run):
    r = tiny_run['results']
    p = r['parameters']
    cmds = p['node_commands']
    assert set(cmds) == {'matcher', 'extractor (map)', 'extractor (query)'}
    assert all('--ros-args' in c for c in cmds.values())
    assert (
        'reliability:=reliable' in cmds['extractor (map)']
        and 'lln/landmarks:=/lln/keyframes' in cmds['extractor (map)']
    )
    assert 'lln/landmarks:=/lln/query' in cmds['extractor (query)'] and 'mode:=localization' in cmds['matcher']
    assert 1 <= p['domain_id'] <= 101 and p['playback'] == 'paced'
    assert r['node_exit_status'] == {'matcher': 0, 'extractor (map)': 0, 'extractor (query)': 0}


def test_outputs_exist(tiny_run):
    from lln_ros.ros import bag

    out = tiny_run['out']
    for name in (
        'results_online.json',
        'results_online.md',
        'answers_online.csv',
        'pr_online.png',
        'map.db',
        'offline/results.json',
        'offline/results.md',
        'logs/matcher.log',
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    for name in ('map_bag', 'query_bag'):
        info = bag.bag_info(out / name)
        assert info['storage'] == 'mcap' and info['topics'] == {
            '/camera/image_raw': {'type': 'sensor_msgs/msg/Image', 'count': FRAMES}
        }
    examples = tiny_run['results']['figures']['examples']
    assert examples and all((out / ex['file']).stat().st_size > 10_000 and ex['pairs'] > 0 for ex in examples)
    assert cv2.imread(str(out / 'pr_online.png')) is not None
    md = (out / 'results_online.md').read_text()
    assert '| P@100%R |' in md and 'agree on every metric' in md
    rows = (out / 'answers_online.csv').read_text().strip().splitlines()
    assert len(rows) == FRAMES + 1 and rows[0].startswith('query,query_file')


# ----------------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    'args, message',
    [
        (['--dataset', 'aligned:/nonexistent/a,/nonexistent/b'], 'does not exist'),
        (['--dataset', 'nordland:x'], 'cannot parse dataset'),
        (['--dataset', 'loop:/x,/y.bmp'], 'two traverses'),
        (['--dataset', 'gardenspoint:/nonexistent/gp'], 'add --download'),
        (['--range', '1:0.5'], '--range'),
        (['--range', 'half'], '--range'),
        (['--top-n', '0'], '--top-n'),
        (['--prefilter-k', '-1'], '--prefilter-k'),
        (['--weights', '/nonexistent.pt'], '--weights'),
    ],
    ids=[
        'missing-folders',
        'unknown-kind',
        'loop',
        'gardenspoint-no-download',
        'range-order',
        'range-text',
        'top-n',
        'prefilter-k',
        'weights',
    ],
)
def test_bad_input_exits_2_before_anything_runs(tiny_dataset, tmp_path, capsys, args, message):
    out = tmp_path / 'out'
    argv = ['--out', str(out)] + (args if '--dataset' in args else ['--dataset', tiny_dataset] + args)
    assert demo.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith('lln-demo: error:') and message in err[-1], err
    assert not out.exists(), 'nothing is written for bad input'


def test_rate_is_the_old_name_of_fps(capsys):
    assert demo.build_parser().parse_args(['--out', 'o', '--rate', '4']).fps == 4.0
    assert 'lln-demo: note: --rate is deprecated here, use --fps' in capsys.readouterr().err
    assert demo.build_parser().parse_args(['--out', 'o']).fps is None  # paced


@pytest.mark.parametrize(
    'args',
    [['--fps', '0'], ['--fps', '-3'], ['--rate', '0'], ['--method', 'nope'], []],
    ids=['fps-zero', 'fps-negative', 'old-rate-zero', 'method', 'no-out'],
)
def test_bad_arguments_exit_2(tmp_path, capsys, args):
    argv = args + (['--out', str(tmp_path / 'o')] if args else [])
    with pytest.raises(SystemExit) as e:
        demo.main(argv)
    assert e.value.code == 2
    assert 'lln-demo: error:' in capsys.readouterr().err


def test_out_must_be_a_folder(tiny_dataset, tmp_path, capsys):
    f = tmp_path / 'file'
    f.write_text('x')
    assert demo.main(['--dataset', tiny_dataset, '--out', str(f)]) == 2
    assert 'is not a folder' in capsys.readouterr().err


def test_no_dataset_anywhere_says_give_dataset(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv('LLN_DATA', raising=False)
    assert demo.main(['--out', str(tmp_path / 'o'), '--download-dir', str(tmp_path / 'gp')]) == 2
    err = capsys.readouterr().err
    assert 'give --dataset SPEC' in err and '--download' in err


def test_default_without_shared_data_is_gardens_point(tmp_path, monkeypatch):
    monkeypatch.delenv('LLN_DATA', raising=False)
    args = demo.build_parser().parse_args(['--out', 'o', '--download', '--download-dir', str(tmp_path / 'gp')])
    spec, frac, why = demo.choose_dataset(args)
    assert spec == f'gardenspoint:{tmp_path / "gp"}' and frac is None and 'downloaded' in why


def test_download_calls_fetch_gardenspoint(tmp_path, monkeypatch, capsys):
    """--download on a Gardens Point folder that lacks its traverses fetches it (here a stub that
    writes a tiny copy; the download itself is tested against a loopback server elsewhere)."""
    import lln_ros.io.download as download

    calls = []

    def fake_fetch(root, url, progress=True, **kw):
        calls.append((str(root), url))
        rng = np.random.default_rng(1)
        for sub in ('day_right', 'night_right'):
            (Path(root) / sub).mkdir(parents=True)
            for i in range(3):
                cv2.imwrite(str(Path(root) / sub / f'{i}.png'), rng.integers(0, 255, (64, 96, 3), np.uint8))
        return ['day_right', 'night_right']

    monkeypatch.setattr(download, 'fetch_gardenspoint', fake_fetch)
    root = tmp_path / 'gp'
    assert (
        demo.main(
            [
                '--dataset',
                f'gardenspoint:{root}',
                '--download',
                '--download-url',
                'http://127.0.0.1:9/x.zip',
                '--out',
                str(tmp_path / 'o'),
                '--check',
            ]
        )
        == 0
    )
    assert calls == [(str(root), 'http://127.0.0.1:9/x.zip')]
    assert '3 map frames, 3 queries' in capsys.readouterr().out


# ------------------------------------------------------------------------------- executables, reruns


def test_executables_from_the_ament_prefix_first(tmp_path, monkeypatch):
    prefix = tmp_path / 'install' / 'lln_ros'
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages').mkdir(parents=True)
    (prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / 'lln_ros').write_text('')
    lib = prefix / 'lib' / 'lln_ros'
    lib.mkdir(parents=True)
    for name in ('extractor', 'matcher', 'lln-bag'):
        (lib / name).write_text('#!/bin/sh\n')
        (lib / name).chmod(0o755)
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(prefix))
    exes, where = demo.find_executables()
    assert exes == {n: [str(lib / n)] for n in ('extractor', 'matcher', 'lln-bag')} and str(prefix) in where
    monkeypatch.delenv('AMENT_PREFIX_PATH')
    exes, where = demo.find_executables()
    assert exes['extractor'] == [str(Path(sys.executable).parent / 'extractor')] and 'console scripts' in where


def test_rerun_replaces_only_its_own_outputs(tmp_path):
    out = tmp_path / 'out'
    (out / 'map_bag').mkdir(parents=True)
    (out / 'map.db').write_text('old map')
    (out / 'matches_online_success1_q3.png').write_text('old')
    (out / 'notes.txt').write_text('mine')
    demo.prepare_out(out)
    assert sorted(p.name for p in out.iterdir()) == ['notes.txt']


# ------------------------------------------------------------------------------------------ Ctrl-C


def _children(pid: int) -> list[int]:
    out = []
    for stat in Path('/proc').glob('[0-9]*/stat'):
        try:
            fields = stat.read_text().rsplit(')', 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def _gone(pid: int) -> bool:
    try:
        state = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()[0]
    except OSError:
        return True
    return state == 'Z'


def test_ctrl_c_stops_every_node(tiny_dataset, tmp_path):
    # played at 1 Hz, so the run lasts long enough for the interrupt to land mid-run on any machine
    proc = subprocess.Popen(
        [*DEMO, '--dataset', tiny_dataset, '--out', str(tmp_path / 'out'), '--no-offline', '--fps', '1'],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        kids = []
        while time.monotonic() < deadline and len(kids) < 3 and proc.poll() is None:
            time.sleep(0.2)
            kids = _children(proc.pid)
        assert len(kids) == 3, (kids, proc.poll())
        time.sleep(2.0)  # the nodes are loading or up
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, err
    assert 'interrupted; the nodes were stopped' in err
    assert all(_gone(pid) for pid in kids), [pid for pid in kids if not _gone(pid)]


# ------------------------------------------------------------------------------ the default dataset


def test_default_dataset_is_the_nordland_test_split(tmp_path):
    shared_data('nordland_trimmed')
    done = run_demo('--out', str(tmp_path / 'o'), '--check', timeout=120)
    assert done.returncode == 0, done.stderr
    assert 'OK: summer-vs-winter[0.7:1]: 1073 map frames, 1073 queries' in done.stdout, done.stdout
    assert 'the Nordland test split' in done.stderr and '--range 0.7:1' in done.stderr
    assert not (tmp_path / 'o').exists()


@pytest.mark.parametrize('prefilter', ['30', '0'], ids=['prefilter30', 'exhaustive'])
def test_nordland_slice_through_the_nodes(tmp_path, prefilter):
    """11 places of the default dataset (64x32 frames upsampled to the network): online == offline,
    with the holistic prefilter and with every map frame scored. (Not the very end: the last 15
    winter frames are one repeated image.)"""
    shared_data('nordland_trimmed')
    out = tmp_path / 'o'
    done = run_demo('--out', str(out), '--range', '0.99:0.993', '--examples', '1', '--prefilter-k', prefilter)
    assert done.returncode == 0, f'{done.stdout}\n{done.stderr}'
    r = json.loads((out / 'results_online.json').read_text())
    assert r['dataset']['refs'] == r['dataset']['queries'] == 11
    assert r['transport']['query']['lost'] == r['transport']['map']['lost'] == 0
    assert r['comparison']['agree'], r['comparison']
    for key, _ in demo.METRICS:
        assert r['online'][key] == r['offline'][key], key


# ------------------------------------------------------------------ the offline side's feature cache


def offline_args(tmp_path, **kw):
    import argparse

    base = dict(top_n=50, method='lln', threads=1, runtime=None, weights='', cache=str(tmp_path / 'cache'))
    base.update(quiet=True, prefilter='landmarks', prefilter_k=100, examples=1)
    return argparse.Namespace(**{**base, **kw})


def test_offline_worker_fills_from_both_ends_the_evaluators_cache(tiny_dataset, tmp_path, extractor):
    """The worker fills from the front, this process from the back once asked to finish; together
    they leave every image's entry, equal to what the evaluator's FeatureCache computes."""
    from lln_ros.eval.demo_offline import CHUNK, OfflineRun
    from lln_ros.io.datasets import aligned
    from lln_ros.io.features import FeatureCache, file_digest

    _, _, rest = tiny_dataset.partition(':')
    ds = aligned(*rest.split(',')[:2], 0)
    paths = [str(p) for p in ds.ref_paths] + [str(p) for p in ds.query_paths]
    assert len(paths) == 2 * FRAMES
    job = OfflineRun(ds, tiny_dataset, offline_args(tmp_path), tmp_path / 'out', job=False)
    report = job.finish(extractor)['cache_fill']
    parts = ('chunks_by_worker_during_online', 'chunks_by_worker_after', 'chunks_by_main_after')
    assert sum(report[key] for key in parts) == -(-len(paths) // CHUNK)
    stored = [FeatureCache(tmp_path / 'cache', extractor)._path(file_digest(p), 288) for p in paths]
    assert all(p.is_file() for p in stored)
    fresh = FeatureCache(tmp_path / 'fresh', extractor).load(paths)
    for p, want in zip(stored, fresh):
        np.testing.assert_allclose(np.load(p).astype(np.float32), want.astype(np.float32), atol=2e-2)
    # a warm cache: the second pass only reads digests, and stop() on a finished worker is harmless
    again = OfflineRun(ds, tiny_dataset, offline_args(tmp_path), tmp_path / 'out', job=False)
    assert again.finish(extractor)['cache_fill']['images'] == len(paths)
    again.stop()


def test_offline_worker_evaluates_as_lln_eval_does(tiny_dataset, tmp_path, extractor):
    """The worker's evaluation is runner.evaluate's: the same ranking as run here, results.json
    written; a failing evaluation comes back as the worker's one-line error."""
    from lln_ros.eval.demo_offline import OfflineRun, run_offline
    from lln_ros.io.datasets import aligned

    _, _, rest = tiny_dataset.partition(':')
    ds = aligned(*rest.split(',')[:2], 0)
    args = offline_args(tmp_path, prefilter='holistic', prefilter_k=5)
    beside = run_offline(
        ds, tiny_dataset, args, tmp_path / 'a', lambda m: None, OfflineRun(ds, tiny_dataset, args, tmp_path / 'a')
    )
    here = run_offline(ds, tiny_dataset, args, tmp_path / 'b', lambda m: None)
    np.testing.assert_array_equal(beside['ranked'], here['ranked'])
    assert beside['summary'] == here['summary'] and (tmp_path / 'a' / 'offline' / 'results.json').is_file()
    assert beside['cache_fill'] and here['cache_fill'] is None
    dying = OfflineRun(ds, tiny_dataset, args, tmp_path / 'c')
    dying.proc.kill()  # long before it has loaded its model
    with pytest.raises(RuntimeError, match='the offline worker died'):
        run_offline(ds, tiny_dataset, args, tmp_path / 'c', lambda m: None, dying)


def test_examples_are_spread_along_the_route_and_skip_dark_frames(tmp_path):
    """pick_examples: one success per stretch of the route, the most confident informative one;
    black and flat frames are passed over even when they score highest."""
    from lln_ros.eval.figures import informative, pick_examples

    rng = np.random.default_rng(1)
    q = 40
    paths = []
    for i in range(q):
        if i % 10 == 0:  # near-black
            img = rng.integers(0, 20, (48, 64, 3)).astype(np.uint8)
        elif i % 10 == 1:  # flat grey
            img = np.full((48, 64, 3), 128, np.uint8)
        else:
            img = rng.integers(0, 256, (48, 64, 3)).astype(np.uint8)
        paths.append(tmp_path / f'{i}.png')
        cv2.imwrite(str(paths[-1]), img)
    assert not informative(paths[0]) and not informative(paths[1]) and informative(paths[2])
    gt = np.eye(q, dtype=bool)
    ranked = np.arange(q)[:, None].repeat(3, 1)
    wrong = np.arange(q) % 4 == 3  # every 4th query answered with another place
    ranked[wrong, 0] = (np.arange(q)[wrong] + 5) % q
    scores = np.zeros((q, 3), np.float32)
    scores[:, 0] = np.linspace(1, 2, q)
    scores[::10, 0] = 100.0  # the dark frames score highest: they must not win
    picked = pick_examples(ranked, scores, gt, paths, 4)
    assert len(picked['success']) == 4 and len(picked['failure']) == 4
    for kind, queries in picked.items():
        assert all(informative(paths[i]) for i in queries), (kind, queries)
        # one per stretch of 10: the most confident informative one is the last of its stretch
        assert [i // 10 for i in queries] == [0, 1, 2, 3], (kind, queries)
    assert all(not wrong[i] for i in picked['success']) and all(wrong[i] for i in picked['failure'])
    assert picked['success'] == [9, 18, 29, 38] and picked['failure'] == [7, 19, 27, 39]


def test_backlog_counts_what_the_next_node_has_not_taken_and_writes_off_a_stall():
    from lln_ros.cli.demo_nodes import Backlog

    sent, done = [5], [2]
    b = Backlog(lambda: sent[0], lambda: done[0], stall=0.3)
    assert b() == 3
    done[0] = 5
    assert b() == 0
    sent[0] = 9
    assert b() == 4  # done moved just now: still waiting
    time.sleep(0.4)
    assert b() == 0  # done has not moved for the stall time: the 4 are written off as lost
    sent[0] = 12
    assert b() == 3  # and the frames after them are limited again, not waved through
    done[0] = 12  # the written-off ones arrived after all: they are taken back
    assert b() == 0
    sent[0] = 20
    assert b() == 8  # no write-off left to hide an outstanding frame


def test_compare_names_the_first_stage_of_a_candidate_difference():
    """A top-1 that the other side never scored is blamed on the first stage both sides ran, with
    the reason that first stage can differ between the two."""
    from lln_ros.eval.online import compare
    from lln_ros.eval.report import METRICS

    summary = {key: 0.5 for key, _ in METRICS}
    scores = np.array([[9.0, 5.0], [8.0, 1.0]])
    online = {'ranked': np.array([[1, 2], [0, 1]]), 'scores': scores, 'summary': summary}
    r = compare(online, np.array([[3, 2], [0, 1]]), scores, summary, {'map': {'lost': 0}}, prefilter='landmarks')
    assert r['same_top1'] == 1 and [c['query'] for c in r['differing_queries']] == [0]
    assert r['differing_queries'][0]['detail'] == "online answer outside the other side's landmarks top-K"
    assert '1 at the landmark first stage' in r['notes'][0] and 'up to the one that crossed' in r['notes'][0]
