"""lln-eval and lln_ros.eval on real pixels: a tiny aligned set cut from the photograph matplotlib
ships, the Gardens Point download against a loopback HTTP server, bad input, and rtabmap_loop."""

import functools
import http.server
import json
import subprocess
import sys
import threading
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

from conftest import shared_data
from lln_ros.cli.eval import main
from lln_ros.core.landmarks import stack_landmarks
from lln_ros.core.lln import LLNHead, head_fingerprint, save_checkpoint
from lln_ros.core.retrieval import rank_all
from lln_ros.eval import METHODS, REPORT_KEYS, Head, evaluate, figures, parse_head
from lln_ros.eval.methods import variant
from lln_ros.eval.report import markdown, shown_path
from lln_ros.io import datasets
from lln_ros.io.download import fetch_gardenspoint

REQUIRED = {'p_at_100r', 'r_at_1', 'r_at_5', 'r_at_10', 'auc_pr', 'r_at_100p', 'extract_ms', 'match_ms_per_pair', 'n'}
FRACTIONS = ('p_at_100r', 'r_at_1', 'r_at_5', 'r_at_10', 'auc_pr', 'r_at_100p')


@pytest.fixture(scope='module', autouse=True)
def one_torch_thread(extractor):
    """One torch thread here: on a 2-core machine shared with other work, 2 threads contend and
    run ~10x slower. torch's setting is process-wide (the session `extractor` sets it when built,
    hence built first), so it is restored for the other test files."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def write_rgb(path, rgb):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))


def crops(photo, count=12, shift=(0, 0), gain=1.0, size=(160, 120)):
    """count non-overlapping windows of the photo (4 rows x 3 columns), optionally shifted / brightened."""
    out = []
    w, h = size
    for i in range(count):
        r, c = divmod(i, 3)
        y, x = 20 + r * 140 + shift[1], 16 + c * 160 + shift[0]
        out.append(np.clip(photo[y : y + h, x : x + w].astype(np.float32) * gain, 0, 255).astype(np.uint8))
    return out


@pytest.fixture(scope='module')
def tiny(tmp_path_factory, photo):
    """12 refs and 12 queries: the same places moved by (8, 6) pixels and 15% brighter."""
    root = tmp_path_factory.mktemp('tiny')
    for i, (ref, query) in enumerate(zip(crops(photo), crops(photo, shift=(8, 6), gain=1.15))):
        write_rgb(root / 'ref' / f'{i}.png', ref)
        write_rgb(root / 'query' / f'{i}.png', query)
    return root


@pytest.fixture(scope='module')
def other_head(extractor, tmp_path_factory):
    """A head checkpoint that stands in for a trained head: the Xavier init (seed 0), then moved."""
    import torch

    head = LLNHead(extractor.backbone.dim)
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in head.parameters():
            p.add_(0.05 * torch.randn(p.shape, generator=generator))
    path = tmp_path_factory.mktemp('head') / 'other.pt'
    save_checkpoint(str(path), head, 'efficientnet_lite0', extractor.backbone.layer, trained=True)
    return path


@pytest.fixture(scope='module')
def tiny_run(tiny, extractor, other_head, tmp_path_factory):
    out = tmp_path_factory.mktemp('eval')
    ds = datasets.parse_spec(f'aligned:{tiny / "ref"},{tiny / "query"},0')
    conf = {
        'top_n': 20,
        'prefilter': 'holistic',
        'prefilter_k': 5,
        'cache_dir': str(out / 'cache'),
        'timing_images': 2,
        'timing_queries': 4,
        'examples': 1,
    }
    run = evaluate(
        [ds],
        extractor,
        conf,
        [Head('other', str(other_head)), Head('untrained', None)],
        out_dir=out / 'results',
        specs=['tiny'],
    )
    return run, out / 'results', ds


def test_landmark_first_stage_reported_for_every_prefilter(tiny_run, extractor):
    """The default first stage (landmarks): every local method reranks its own landmark top-K, and
    the dataset entry reports recall@K and ms/query of the holistic and landmark first stages."""
    _, out, ds = tiny_run
    run = evaluate(
        [ds],
        extractor,
        {
            'methods': 'holistic,lln',
            'top_n': 20,
            'prefilter_k': 5,
            'plots': False,
            'cache_dir': str(out.parent / 'cache'),
            'timing_images': 1,
            'timing_queries': 1,
            'timing_repeats': 1,
        },
    )
    entry = run.results['datasets']['ref-vs-query']
    assert run.results['parameters']['prefilter'] == 'landmarks'
    stages = entry['first_stage']
    assert set(stages) == {'holistic', 'landmarks', 'lln-weighted sum'}
    for st in stages.values():
        assert set(st['recall_at']) == {'1', '5', '10'} and st['ms_per_query'] > 0  # 12 refs: K <= 12
        assert 0 <= st['recall_at']['1'] <= st['recall_at']['5'] <= st['recall_at']['10'] <= 1
    ranked, _ = run.datasets['ref-vs-query'].rankings['lln']
    assert ranked.shape == (12, 5) and (ranked >= 0).all()
    assert 'First stage (lln landmarks)' in markdown(run.results)
    assert '| lln-weighted sum |' in markdown(run.results)


def test_weighted_sum_is_the_papers_embedding_of_the_head():
    """The learned holistic first stage ranks by lln.embed of each image's own feature map: unit
    vectors, one per image, whatever its grid; a head that weights every cell alike gives the
    normalised mean of the normalised features."""
    import torch

    from lln_ros.eval.first_stage import weighted_sums

    rng = np.random.default_rng(0)
    feats = [rng.normal(size=(8, 3, 4)).astype(np.float16), rng.normal(size=(8, 2, 5)).astype(np.float16)]

    class Flat(torch.nn.Module):
        def forward(self, f):
            return torch.ones(f.shape[0], *f.shape[2:])

    out = weighted_sums(Flat(), feats)
    assert out.shape == (2, 8) and np.allclose(np.linalg.norm(out, axis=1), 1, atol=1e-6)
    f = feats[1].astype(np.float32)
    mean = (f / np.linalg.norm(f, axis=0, keepdims=True)).sum((1, 2))
    assert np.allclose(out[1], mean / np.linalg.norm(mean), atol=1e-5)


def test_results_json_has_the_required_structure(tiny_run):
    run, out, ds = tiny_run
    results = json.loads((out / 'results.json').read_text())
    assert results == json.loads(json.dumps(run.results))  # what is returned is what is written
    entry = results['datasets']['ref-vs-query']
    assert entry['queries'] == 12 and entry['refs'] == 12
    assert list(entry['methods']) == ['holistic', 'lln[other]', 'lln[untrained]', 'act', 'rand', 'all']
    for row, m in entry['methods'].items():
        assert REQUIRED <= set(m), row
        for key in FRACTIONS:
            assert 0.0 <= m[key] <= 1.0, (row, key, m[key])
        assert m['extract_ms'] > 0 and m['match_ms_per_pair'] > 0
    m = entry['methods']
    assert m['holistic']['n'] == 1
    assert m['lln[other]']['n'] == m['act']['n'] == m['rand']['n'] == 20
    assert m['all']['n'] == 12 * 9  # 160x120 crops -> 384x288 at the network -> a 12x9 grid
    assert entry['grid'] == [9, 12]
    assert results['parameters']['top_n'] == 20 and results['parameters']['prefilter_k'] == 5
    assert len(entry['recall_at_k_holistic']) == 12
    # per query: every row's answers, and its wrong ones are exactly what P@100%R counts
    pq = entry['per_query']
    assert len(pq['with_match']) == entry['queries_with_match'] and set(pq['top1']) == set(m)
    for row, wrong in pq['wrong'].items():
        assert len(pq['top1'][row]) == 12 and set(wrong) <= set(pq['with_match'])
        assert 1 - len(wrong) / len(pq['with_match']) == pytest.approx(m[row]['p_at_100r']), row
        truth = np.asarray(ds.gt, bool)
        assert all(pq['top1'][row][q] < 0 or not truth[q, pq['top1'][row][q]] for q in wrong), row


def test_easy_set_is_solved(tiny_run):
    run, _, _ = tiny_run
    m = run.results['datasets']['ref-vs-query']['methods']
    for row in ('holistic', 'lln[other]', 'lln[untrained]', 'all'):
        assert m[row]['p_at_100r'] >= 0.75, (row, m[row])
        assert m[row]['r_at_5'] >= m[row]['r_at_1']
    curve = run.results['datasets']['ref-vs-query']['recall_at_k_holistic']
    assert all(b >= a for a, b in zip(curve, curve[1:])) and curve[-1] == 1.0


def test_every_local_method_reranks_the_same_holistic_top_k(tiny_run):
    run, _, _ = tiny_run
    d = run.datasets['ref-vs-query']
    top = d.holistic_full[:, :5]
    for row, (ranked, scores) in d.rankings.items():
        if row == 'holistic':
            continue
        assert ranked.shape == (12, 5)
        assert all(set(a) == set(b) for a, b in zip(ranked, top)), row
        assert (np.diff(scores, axis=1) <= 1e-6).all()  # best first


def test_rankings_equal_direct_extraction(tiny_run, tiny, extractor):
    """The cached-feature path gives the ranking a plain Extractor gives from the image files."""
    from lln_ros.io.image import load_image

    run, _, ds = tiny_run
    v = variant(extractor, 'all', 20)
    qs = v.extract_batch([load_image(str(p)) for p in ds.query_paths])
    rs = v.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    ranked, _ = rank_all(qs, stack_landmarks(rs), 5)
    mine = run.datasets['ref-vs-query'].rankings['all'][0]
    assert (ranked[:, 0] == mine[:, 0]).mean() >= 11 / 12  # features are cached as float16


def test_heads_are_separate_rows(tiny_run, extractor, other_head):
    run, _, _ = tiny_run
    m = run.results['datasets']['ref-vs-query']['methods']
    xavier = head_fingerprint(LLNHead(extractor.backbone.dim))
    assert m['lln[untrained]']['head_trained'] is False and m['lln[untrained]']['head_fingerprint'] == xavier
    assert m['lln[other]']['head_trained'] is True and m['lln[other]']['head_fingerprint'] != xavier
    assert m['lln[other]']['weights'] == str(other_head)
    heads = run.results['parameters']['heads']
    assert set(heads) == {'other', 'untrained'} and heads['untrained']['weights'] == ''


def test_pictures_and_markdown(tiny_run):
    run, out, _ = tiny_run
    figs = run.results['datasets']['ref-vs-query']['figures']
    assert {'pr', 'recall_at_k', 'heatmaps'} <= set(figs) and figs['examples']
    assert len(run.figures) >= 4
    for name in run.figures:
        img = cv2.imread(str(out / name))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 300, name
    md = (out / 'results.md').read_text()
    for row in ('holistic', 'lln[other]', 'lln[untrained]', 'act', 'rand', 'all'):
        assert f'| {row} |' in md
    assert '## Parameters' in md and 'prefilter_k: `5`' in md and '(ref-vs-query_pr.png)' in md
    # the held-out column: other.pt lists no training images, the Xavier head trained on nothing
    assert '| lln[other] | unknown |' in md and '| lln[untrained] | untrained |' in md and '| act | - |' in md


def test_every_method_has_its_own_colour_and_its_sequence_row_shares_it():
    """results.md's plot of 15 rows: no two methods alike; X+seq in X's colour, dash-dotted."""
    rows = ['holistic', 'lln[trained]', 'lln[untrained]', 'act', 'rand', 'all', 'sad', 'seqslam']
    rows += [r + '+seq' for r in rows if r not in ('sad', 'seqslam')]
    colours = figures._colours(rows)
    methods = [r for r in rows if not r.endswith('+seq')]
    assert len({str(colours[r]) for r in methods}) == len(methods)
    assert all(colours[r + '+seq'] == colours[r] for r in methods if r + '+seq' in rows)
    assert figures._line('act+seq', '-') == '-.' and figures._line('act', '-') == '-'


def test_held_out_status_compares_the_images_a_checkpoint_lists(tiny, tmp_path):
    """A head's status on a dataset comes from the image keys its checkpoint lists; a key names a
    file by its last three path components, so the same data in another folder is still recognised."""
    ds = datasets.parse_spec(f'aligned:{tiny / "ref"},{tiny / "query"},0')
    moved = tmp_path / 'elsewhere' / tiny.name
    moved.mkdir(parents=True)
    for side in ('ref', 'query'):
        (moved / side).mkdir()
        for f in (tiny / side).iterdir():
            (moved / side / f.name).write_bytes(f.read_bytes())
    same = datasets.parse_spec(f'aligned:{moved / "ref"},{moved / "query"},0')
    refs, queries = datasets.image_keys(ds.ref_paths), datasets.image_keys(ds.query_paths)
    assert datasets.image_keys(same.ref_paths) == refs and not set(refs) & set(queries)
    n = len(ds.ref_paths) + len(ds.query_paths)

    def status(seen, **meta):
        return Head('h', 'h.pt', None, {'seen_images': seen, **meta}).held_out(same)

    assert status({'train': refs, 'val': []}) == {
        'images': n,
        'status': 'trained on',
        'trained': len(refs),
        'validated': 0,
    }
    assert status({'train': ['0' * 16], 'val': queries})['status'] == 'validated on'
    assert status({'train': ['0' * 16], 'val': []}) == {'images': n, 'status': 'held out', 'trained': 0, 'validated': 0}
    assert status(None)['status'] == 'unknown'
    assert status({'train': refs, 'val': []}, trained=False)['status'] == 'untrained'


def test_parse_head():
    assert (parse_head('trained=a/b.pt').label, parse_head('trained=a/b.pt').weights) == ('trained', 'a/b.pt')
    assert parse_head('untrained=').weights is None and parse_head('xavier').label == 'untrained'
    assert parse_head('runs/best.pt').label == 'best' and parse_head('x.pt', 'mine').label == 'mine'


# ------------------------------------------------------------------------------------------------ CLI


def run_cli(*args):
    return main([str(a) for a in args])


def test_cli_trained_vs_untrained_in_one_command(tiny, tiny_run, other_head, tmp_path, capsys):
    """--heads and --weights/--label give one lln row per head, next to the head-free baselines."""
    _, results_dir, _ = tiny_run
    cache = results_dir.parent / 'cache'  # features from tiny_run: no backbone pass but the timing
    rc = run_cli(
        '--dataset',
        f'aligned:{tiny / "ref"},{tiny / "query"},0',
        '--methods',
        'holistic,lln,all',
        '--top-n',
        20,
        '--prefilter-k',
        5,
        '--out',
        tmp_path / 'a',
        '--cache',
        cache,
        '--heads',
        f'trained={other_head},untrained=',
        '--timing-images',
        1,
        '--timing-queries',
        2,
        '--examples',
        0,
        '--heatmap-images',
        2,
        '--threads',
        1,
        '--quiet',
    )
    assert rc == 0, capsys.readouterr().err
    results = json.loads((tmp_path / 'a' / 'results.json').read_text())
    entry = results['datasets']['ref-vs-query']
    assert list(entry['methods']) == ['holistic', 'lln[trained]', 'lln[untrained]', 'all']
    assert results['parameters']['command'].startswith('lln-eval --dataset aligned:')
    assert (tmp_path / 'a' / 'ref-vs-query_heatmaps.png').is_file()

    rc = run_cli(
        '--dataset',
        f'aligned:{tiny / "ref"},{tiny / "query"},0',
        '--methods',
        'lln',
        '--top-n',
        20,
        '--prefilter-k',
        5,
        '--out',
        tmp_path / 'b',
        '--cache',
        cache,
        '--weights',
        other_head,
        '--label',
        'mine',
        '--weights',
        '',
        '--label',
        'xavier',
        '--timing-images',
        1,
        '--timing-queries',
        2,
        '--no-plots',
        '--threads',
        1,
        '--quiet',
    )
    assert rc == 0, capsys.readouterr().err
    methods = json.loads((tmp_path / 'b' / 'results.json').read_text())['datasets']['ref-vs-query']['methods']
    assert list(methods) == ['lln[mine]', 'lln[xavier]']
    assert methods['lln[mine]']['p_at_100r'] == entry['methods']['lln[trained]']['p_at_100r']
    assert not list((tmp_path / 'b').glob('*.png'))


def test_cli_similarity_center_reaches_every_rerank(tiny, tiny_run, extractor, tmp_path, capsys):
    """--similarity-center: the rows are S on centred sets (rank_all(center=True)), and the report says so."""
    _, results_dir, ds = tiny_run
    args = ['--dataset', f'aligned:{tiny / "ref"},{tiny / "query"},0', '--methods', 'act', '--top-n', 20]
    args += ['--prefilter-k', 0, '--cache', results_dir.parent / 'cache', '--timing-images', 1]
    args += ['--timing-queries', 1, '--examples', 0, '--no-plots', '--threads', 1, '--quiet']
    assert run_cli(*args, '--similarity-center', '--out', tmp_path / 'c') == 0, capsys.readouterr().err
    results = json.loads((tmp_path / 'c' / 'results.json').read_text())
    assert results['parameters']['similarity_center'] is True
    from lln_ros.io.image import load_image

    v = variant(extractor, 'act', 20)
    refs = stack_landmarks(v.extract_batch([load_image(str(p)) for p in ds.ref_paths]))
    queries = v.extract_batch([load_image(str(p)) for p in ds.query_paths])
    ranked, _ = rank_all(queries, refs, 0, center=True)
    top1 = np.mean(ds.gt[np.arange(12), ranked[:, 0]])
    # within one query: features are cached as float16
    assert abs(results['datasets']['ref-vs-query']['methods']['act']['p_at_100r'] - top1) <= 1 / 12 + 1e-9


def test_cli_exhaustive_prefilter_scores_every_reference(tiny, tiny_run, extractor, tmp_path, capsys):
    """--prefilter-k 0: every local method ranks all 12 references by S (no holistic cap), X+seq too,
    and the report says so."""
    _, results_dir, ds = tiny_run
    rc = run_cli(
        '--dataset',
        f'aligned:{tiny / "ref"},{tiny / "query"},0',
        '--methods',
        'holistic,act',
        '--top-n',
        20,
        '--prefilter-k',
        0,
        '--sequence',
        3,
        '--out',
        tmp_path / 'x',
        '--cache',
        results_dir.parent / 'cache',
        '--timing-images',
        1,
        '--timing-queries',
        2,
        '--examples',
        0,
        '--no-plots',
        '--threads',
        1,
        '--quiet',
    )
    assert rc == 0, capsys.readouterr().err
    results = json.loads((tmp_path / 'x' / 'results.json').read_text())
    assert results['parameters']['prefilter_k'] == 0
    assert list(results['datasets']['ref-vs-query']['methods']) == ['holistic', 'act', 'holistic+seq', 'act+seq']
    from lln_ros.io.image import load_image

    v = variant(extractor, 'act', 20)
    refs = v.extract_batch([load_image(str(p)) for p in ds.ref_paths])
    queries = v.extract_batch([load_image(str(p)) for p in ds.query_paths])
    ranked, _ = rank_all(queries, stack_landmarks(refs), 0)
    assert ranked.shape == (12, 12)  # every reference, by S
    top1 = np.mean(ds.gt[np.arange(12), ranked[:, 0]])
    # within one query: features are cached as float16
    assert abs(results['datasets']['ref-vs-query']['methods']['act']['p_at_100r'] - top1) <= 1 / 12 + 1e-9
    run = evaluate(
        [datasets.parse_spec(f'aligned:{tiny / "ref"},{tiny / "query"},0')],
        extractor,
        {
            'methods': 'act',
            'top_n': 20,
            'prefilter_k': 0,
            'sequence': 3,
            'plots': False,
            'cache_dir': str(results_dir.parent / 'cache'),
            'timing_images': 1,
            'timing_queries': 1,
        },
    )
    rankings = run.datasets['ref-vs-query'].rankings
    assert rankings['act'][0].shape == rankings['act+seq'][0].shape == (12, 12)
    assert (np.sort(rankings['act'][0], axis=1) == np.arange(12)).all()
    assert (ranked[:, 0] == rankings['act'][0][:, 0]).mean() >= 11 / 12
    md = (tmp_path / 'x' / 'results.md').read_text()
    assert 'scores every reference' in md and 'Exhaustive (prefilter_k 0)' in md
    assert (
        run_cli(
            '--dataset',
            f'aligned:{tiny / "ref"},{tiny / "query"},0',
            '--prefilter-k',
            -1,
            '--out',
            tmp_path / 'y',
            '--quiet',
        )
        == 2
    )
    assert '--prefilter-k at least 0' in capsys.readouterr().err


def test_sequence_rows_only_where_the_dataset_is_a_sequence(tiny, tiny_run, tmp_path, capsys):
    """A VPR-Bench folder is not a route by default: --sequence rows and seqslam are skipped with a
    note (in results.json and results.md); sequence=1 in the spec brings them back. The same images
    as an aligned spec (a sequence by default) get them, and sequence=0 takes them away."""
    import shutil

    _, results_dir, _ = tiny_run
    vpr = tmp_path / 'vpr'
    shutil.copytree(tiny, vpr)
    rows = np.empty((12, 2), object)
    for q in range(12):
        rows[q] = [q, [q]]
    np.save(vpr / 'ground_truth_new.npy', rows, allow_pickle=True)

    def rows_of(spec, out):
        rc = run_cli(
            '--dataset',
            spec,
            '--methods',
            'holistic,act,seqslam',
            '--top-n',
            20,
            '--prefilter-k',
            5,
            '--sequence',
            3,
            '--out',
            tmp_path / out,
            '--cache',
            results_dir.parent / 'cache',
            '--timing-images',
            1,
            '--timing-queries',
            1,
            '--timing-repeats',
            1,
            '--no-plots',
            '--quiet',
        )
        assert rc == 0, capsys.readouterr().err
        entry = next(iter(json.loads((tmp_path / out / 'results.json').read_text())['datasets'].values()))
        return entry, (tmp_path / out / 'results.md').read_text()

    entry, md = rows_of(f'vprbench:{vpr}', 'a')
    assert list(entry['methods']) == ['holistic', 'act'] and entry['sequence'] is False
    assert len(entry['notes']) == 1 and 'not a sequence' in entry['notes'][0]
    assert '--sequence 3 rows and seqslam skipped' in entry['notes'][0]
    assert 'Note: --sequence 3 rows and seqslam skipped' in md and '+seq' not in md.split('## Parameters')[0]
    entry, _ = rows_of(f'vprbench:{vpr},sequence=1', 'b')
    assert list(entry['methods']) == ['holistic', 'act', 'seqslam', 'holistic+seq', 'act+seq']
    assert entry['sequence'] is True and entry['notes'] == []
    entry, _ = rows_of(f'aligned:{vpr / "ref"},{vpr / "query"},0', 'c')
    assert list(entry['methods']) == ['holistic', 'act', 'seqslam', 'holistic+seq', 'act+seq']
    entry, _ = rows_of(f'aligned:{vpr / "ref"},{vpr / "query"},0,sequence=0', 'd')
    assert list(entry['methods']) == ['holistic', 'act'] and entry['notes']


def make_bad_inputs(root: Path, photo) -> dict:
    good = crops(photo, 3)
    for i, im in enumerate(good):
        write_rgb(root / 'a' / f'{i}.png', im)
        write_rgb(root / 'b' / f'{i}.png', im)
        write_rgb(root / 'short' / f'{i}.png', im)
        write_rgb(root / 'broken' / f'{i}.png', im)
        write_rgb(root / 'seq' / f'{i}.png', im)
    (root / 'short' / '2.png').unlink()
    (root / 'broken' / '1.png').write_bytes(b'\x89PNG\r\n\x1a\n' + b'truncated')
    np.save(root / 'gt4.npy', np.zeros((4, 4), np.uint8))
    a = root / 'a'
    return {
        'missing folder': (f'aligned:{a},{root / "nope"}', 'does not exist'),
        'unequal lengths': (f'aligned:{a},{root / "short"}', 'differ in length'),
        'ground truth shape': (f'loop:{root / "seq"},{root / "gt4.npy"}', 'must be 3x3'),
        'unreadable image': (f'aligned:{a},{root / "broken"}', 'cannot read image'),
        'missing vprbench gt': (f'vprbench:{root}', 'does not exist'),
        'unknown kind': ('nordland:x', 'cannot parse dataset'),
        'unknown option': (f'loop:{root / "seq"},{root / "gt4.npy"},drop=blank', "unknown option 'drop' for loop"),
        'bad sequence option': (f'aligned:{a},{root / "b"},sequence=yes', 'sequence= takes 0 or 1'),
        'bad drop mode': (f'aligned:{a},{root / "b"},drop=dark', 'drop= takes none or'),
        'gardens point layout': (f'gardenspoint:{root / "gp"}', 'add --download'),
    }


@pytest.fixture(scope='module')
def bad_inputs(tmp_path_factory, photo):
    root = tmp_path_factory.mktemp('bad')
    return root, make_bad_inputs(root, photo)


@pytest.mark.parametrize(
    'case',
    [
        'missing folder',
        'unequal lengths',
        'ground truth shape',
        'unreadable image',
        'missing vprbench gt',
        'unknown kind',
        'unknown option',
        'bad sequence option',
        'bad drop mode',
        'gardens point layout',
    ],
)
def test_bad_dataset_is_one_line_before_any_extraction(case, bad_inputs, tmp_path, capsys):
    root, cases = bad_inputs
    spec, message = cases[case]
    good = f'aligned:{root / "a"},{root / "b"}'
    # the bad dataset comes second: the good one must not have been extracted first
    rc = run_cli('--dataset', good, '--dataset', spec, '--out', tmp_path / 'out', '--cache', tmp_path / 'cache')
    err = capsys.readouterr().err
    assert rc == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('lln-eval: error:') and message in lines[0], err
    assert not (tmp_path / 'cache').exists() and not (tmp_path / 'out').exists()


@pytest.mark.parametrize(
    'args, message',
    [
        (['--methods', 'lln,delf'], "unknown method(s) ['delf']"),
        (['--range', '0.5'], '--range must be START:END'),
        (['--range', '0.7:1.5'], '0 <= START < END <= 1'),
        (['--label', 'x'], '--label given 1 times'),
        (['--heads', 'trained'], 'LABEL=CKPT'),
        (['--heads', 'a=,a=xavier'], 'distinct'),
        (['--weights', 'missing.pt'], 'checkpoint not found'),
        (['--top-n', '0'], 'at least 1'),
    ],
)
def test_bad_options_are_one_line(args, message, bad_inputs, tmp_path, capsys):
    root, _ = bad_inputs
    rc = run_cli(
        '--dataset',
        f'aligned:{root / "a"},{root / "b"}',
        '--out',
        tmp_path / 'out',
        '--cache',
        tmp_path / 'cache',
        *args,
    )
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and message in err, err
    assert not (tmp_path / 'cache').exists()


def test_module_entry_point_exits_2(tmp_path):
    out = subprocess.run(
        [
            sys.executable,
            '-m',
            'lln_ros.cli.eval',
            '--dataset',
            f'aligned:{tmp_path / "x"},{tmp_path / "y"}',
            '--out',
            str(tmp_path / 'o'),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and 'does not exist' in out.stderr and 'Traceback' not in out.stderr


# ------------------------------------------------------------------------------------------- download


class Server:
    """http.server on 127.0.0.1 (ephemeral port) in a thread, serving one folder; counts requests."""

    def __init__(self, folder: Path):
        outer = self
        self.requests = []

        class Handler(http.server.SimpleHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):
                outer.requests.append(self.path)
                super().do_GET()

        self.httpd = http.server.ThreadingHTTPServer(
            ('127.0.0.1', 0), functools.partial(Handler, directory=str(folder))
        )
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()
        self.url = f'http://127.0.0.1:{self.httpd.server_address[1]}'

    def close(self):
        self.httpd.shutdown()
        self.httpd.server_close()
        self.thread.join(5)


def make_zip(path: Path, photo, folders=('day_left', 'day_right', 'night_right'), top: str = '', frames=4):
    """A GardensPoint_Walking.zip look-alike: each traverse folder holds `frames` JPEGs (same places,
    night = darker), named like the real archive."""
    with zipfile.ZipFile(path, 'w') as z:
        for f in folders:
            gain = 0.6 if f.startswith('night') else 1.0
            for i, im in enumerate(crops(photo, frames, gain=gain)):
                ok, buf = cv2.imencode('.jpg', cv2.cvtColor(im, cv2.COLOR_RGB2BGR))
                z.writestr(f'{top}{f}/Image{i:03d}.jpg', buf.tobytes())
        z.writestr(f'{top}README.txt', 'Gardens Point Walking (test copy)')


@pytest.fixture(scope='module')
def server(tmp_path_factory, photo):
    served = tmp_path_factory.mktemp('served')
    make_zip(served / 'GardensPoint_Walking.zip', photo)
    make_zip(served / 'nested.zip', photo, top='GardensPoint_Walking/')
    make_zip(served / 'no_night.zip', photo, folders=('day_left', 'day_right'))
    (served / 'garbage.zip').write_bytes(b'<html>not found</html>' * 20)
    s = Server(served)
    yield s
    s.close()


def test_download_then_evaluate(server, tmp_path, capsys):
    root = tmp_path / 'gp'
    url = f'{server.url}/GardensPoint_Walking.zip'
    before = len(server.requests)
    rc = run_cli(
        '--dataset',
        f'gardenspoint:{root}',
        '--download',
        '--download-url',
        url,
        '--methods',
        'holistic,all',
        '--top-n',
        10,
        '--prefilter-k',
        3,
        '--out',
        tmp_path / 'out',
        '--cache',
        tmp_path / 'cache',
        '--timing-images',
        1,
        '--timing-queries',
        2,
        '--examples',
        1,
        '--heatmap-images',
        0,
        '--threads',
        1,
    )
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert server.requests[before:] == ['/GardensPoint_Walking.zip']
    assert 'downloading' in captured.err
    assert sorted(p.name for p in root.iterdir()) == ['day_left', 'day_right', 'night_right']  # no leftovers
    assert len(list((root / 'night_right').glob('*.jpg'))) == 4
    entry = json.loads((tmp_path / 'out' / 'results.json').read_text())['datasets']
    entry = entry['gardenspoint-day_right-vs-night_right']
    assert entry['queries'] == 4 and set(entry['methods']) == {'holistic', 'all'}
    assert entry['methods']['all']['p_at_100r'] >= 0.75  # +-2 frames of 4: nearly everything is right

    # the layout is there now: a second run does not download again
    rc = run_cli(
        '--dataset',
        f'gardenspoint:{root},day_left,night_right',
        '--download',
        '--download-url',
        url,
        '--out',
        tmp_path / 'out2',
        '--check',
    )
    assert rc == 0 and len(server.requests) == before + 1


def test_download_nested_archive(server, tmp_path):
    got = fetch_gardenspoint(tmp_path / 'gp', f'{server.url}/nested.zip', progress=False)
    assert got == ['day_left', 'day_right', 'night_right']
    ds = datasets.gardenspoint(tmp_path / 'gp')
    assert len(ds.query_paths) == 4 and ds.gt.shape == (4, 4)


@pytest.mark.parametrize(
    'name, message',
    [
        ('garbage.zip', 'is not a zip archive'),
        ('no_night.zip', 'lacks the Gardens Point folders'),
        ('missing.zip', 'cannot download'),
    ],
)
def test_download_failures_are_one_line(name, message, server, tmp_path, capsys):
    root = tmp_path / 'gp'
    rc = run_cli(
        '--dataset',
        f'gardenspoint:{root}',
        '--download',
        '--download-url',
        f'{server.url}/{name}',
        '--out',
        tmp_path / 'out',
        '--cache',
        tmp_path / 'cache',
        '--quiet',
    )
    err = capsys.readouterr().err
    assert rc == 2 and message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / 'cache').exists() and list(root.iterdir()) == []  # nothing half-written


def test_download_waits_for_every_other_dataset(server, bad_inputs, tmp_path, capsys):
    root, cases = bad_inputs
    before = len(server.requests)
    rc = run_cli(
        '--dataset',
        f'gardenspoint:{tmp_path / "gp"}',
        '--download',
        '--download-url',
        f'{server.url}/GardensPoint_Walking.zip',
        '--dataset',
        cases['unequal lengths'][0],
        '--out',
        tmp_path / 'out',
    )
    assert rc == 2 and 'differ in length' in capsys.readouterr().err
    assert len(server.requests) == before  # the bad second dataset stopped the run before any download


# ------------------------------------------------------------------------------------------ real data


def test_rtabmap_loop(tmp_path, capsys):
    """The loop protocol on the real 84-frame sequence: every method, pictures, sane figures."""
    root = shared_data('rtabmap_loop')
    out = tmp_path / 'out'
    rc = run_cli(
        '--dataset',
        f'loop:{root},{root / "samples_GT.bmp"}',
        '--out',
        out,
        '--cache',
        tmp_path / 'cache',
        '--timing-images',
        2,
        '--timing-queries',
        5,
        '--examples',
        1,
        '--heatmap-images',
        3,
        '--quiet',
    )
    assert rc == 0, capsys.readouterr().err
    results = json.loads((out / 'results.json').read_text())
    entry = results['datasets']['rtabmap_loop']
    assert entry['queries'] == 84 and entry['queries_with_match'] == 44 and entry['info']['min_gap'] == 10
    assert list(entry['methods']) == list(METHODS)
    for row, m in entry['methods'].items():
        assert set(REPORT_KEYS) <= set(m)
        for key in FRACTIONS:
            assert 0.0 <= m[key] <= 1.0
        # an easy indoor loop: every method finds most revisits (measured: 0.86 .. 0.93)
        assert m['p_at_100r'] >= 0.7, (row, m)
    assert entry['methods']['all']['n'] == 108 and entry['methods']['lln']['n'] == 50
    curve = entry['recall_at_k_holistic']
    assert all(b >= a for a, b in zip(curve, curve[1:])) and curve[29] >= 0.95
    figs = entry['figures']
    kinds = [ex['kind'] for ex in figs['examples']]
    assert 'success' in kinds and 'failure' in kinds and any('truth_file' in ex for ex in figs['examples'])
    for name in [figs['pr'], figs['recall_at_k'], figs['heatmaps']] + [ex['file'] for ex in figs['examples']]:
        assert cv2.imread(str(out / name)) is not None, name
    md = (out / 'results.md').read_text()
    assert all(f'| {row}' in md for row in METHODS)


def test_untrained_head_has_the_checkpoint_architecture(extractor, tmp_path):
    """ "trained vs untrained" must differ only in training: the untrained head copies the architecture
    and init seed of the checkpoint it is compared with."""
    from lln_ros.eval import load_heads

    dim = extractor.backbone.dim
    path = tmp_path / 'small.pt'
    save_checkpoint(
        str(path),
        LLNHead(dim, {'channels': 16, 'kernel_sizes': (1, 3), 'seed': 3}),
        'efficientnet_lite0',
        extractor.backbone.layer,
    )
    trained, untrained = load_heads(extractor, [Head('t', str(path)), Head('u', None)])
    assert untrained.module.conf['channels'] == 16 and untrained.module.conf['kernel_sizes'] == (1, 3)
    assert head_fingerprint(untrained.module) == head_fingerprint(trained.module)  # same init, never trained
    assert untrained.trained is False and trained.trained is True
    only = load_heads(extractor, [Head('u', None)])[0]
    assert head_fingerprint(only.module) == head_fingerprint(LLNHead(dim))
    with pytest.raises(Exception, match='trained for layer'):
        other = 'stage7' if extractor.backbone.layer != 'stage7' else 'stage6'
        save_checkpoint(str(tmp_path / 'wrong.pt'), LLNHead(dim), 'efficientnet_lite0', other)
        load_heads(extractor, [Head('w', str(tmp_path / 'wrong.pt'))])


def test_report_shows_paths_inside_the_working_directory_relative(tmp_path, monkeypatch):
    """results.md is committed: a head's weights under the repo show as a repo path, never as the
    absolute path of the machine that ran it; paths outside it and relative ones stay as given."""
    monkeypatch.chdir(tmp_path)
    assert shown_path(str(tmp_path / 'lln_ros' / 'weights' / 'h.pt')) == 'lln_ros/weights/h.pt'
    outside = str(tmp_path.parent / 'elsewhere.pt')
    assert shown_path(outside) == outside
    assert shown_path('out/best.pt') == 'out/best.pt'
    assert shown_path(None) is None


def test_recall_at_k_labels_say_what_each_curve_ranks():
    """Only a rerank of the first stage (and its sequence search) says 'reranked'; the whole-image
    peers and holistic+seq rank every reference."""
    label = figures._recall_label
    assert label('lln[trained]', 30) == 'lln[trained] (its first-stage top-30, reranked)'
    assert 'reranked' in label('act+seq', 30) and 'act' in label('act+seq', 30)
    for row in ('sad', 'seqslam', 'holistic+seq'):
        assert 'reranked' not in label(row, 30) and 'every reference' in label(row, 30), row
