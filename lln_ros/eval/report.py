"""The one report stack of lln-eval, lln-demo and `make results` (scripts/results_md.py): number
formats, JSON, markdown tables, the online-vs-offline table and the per-query answers CSV.

One convention everywhere: every metric (P@100%R, R@100%P, AUC-PR, R@K) is printed as a percentage
of the queries with one decimal (`pct`), in tables, figure legends and text alike; JSON keeps fractions.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np

from ..core import metrics
from ..core.retrieval import default_conf as retrieval_defaults

# (results key, label) of every metric a report shows, in the order shown
METRICS = (
    ('p_at_100r', 'P@100%R'),
    ('r_at_100p', 'R@100%P'),
    ('auc_pr', 'AUC-PR'),
    ('r_at_1', 'R@1'),
    ('r_at_5', 'R@5'),
    ('r_at_10', 'R@10'),
)


def shown_path(path: str | None) -> str | None:
    """A path as a report shows it: relative to the working directory when inside it (the report is
    committed with the repo; /home/someone/... says nothing to its readers), else as given."""
    if not path or not os.path.isabs(path):
        return path
    rel = os.path.relpath(path)
    return path if rel.startswith('..') else rel


def finite(x):
    """x, or None when x is a non-finite float (JSON has no NaN / inf)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


def pct(x) -> str:
    """A fraction as a percentage with one decimal; '–' for None / NaN / inf."""
    if x is None or (isinstance(x, (float, np.floating)) and not math.isfinite(float(x))):
        return '–'
    return f'{100 * x:.1f}'


def ms(x) -> str:
    if x is None:
        return '–'
    return f'{x:.1f}' if x >= 10 else f'{x:.3g}'


def num1(x) -> str:
    return '–' if x is None else f'{x:.1f}'


def jsonable(x):
    """x with numpy scalars / arrays, tuples and paths made JSON types, non-finite floats None."""
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return finite(float(x))
    if isinstance(x, np.ndarray):
        return jsonable(x.tolist())
    if isinstance(x, Path):
        return str(x)
    return x


def write_json(results: dict, path) -> None:
    """Atomically: a reader never sees half a file."""
    tmp = Path(f'{path}.tmp')
    tmp.write_text(json.dumps(jsonable(results), indent=1, allow_nan=False) + '\n')
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------ lln-eval


def held_out_text(h: dict | None) -> str:
    """A head's held-out status on a dataset (Head.held_out) in words; '-' for a row without a head."""
    if not h:
        return '-'
    if h['status'] in ('trained on', 'validated on'):
        n = h['trained'] if h['status'] == 'trained on' else h['validated']
        return f'{h["status"]} ({n} of {h["images"]} images)'
    return h['status']


def seen_by(rows: dict, row: str) -> str:
    """The `this data` cell of a row: its head's held-out status on the dataset (an X+seq row: X's)."""
    return held_out_text(rows.get(rows[row].get('sequence_of', row), {}).get('held_out'))


def markdown(results: dict) -> str:
    """The results as markdown: one table per dataset, every method, the parameters, the figures."""
    p = results.get('parameters', {})
    lines = ['# lln-eval results', '']
    prefiltered = p.get('prefilter_k', retrieval_defaults['prefilter_k'])  # an older results.json lacks it
    # an older results.json has no 'prefilter': its first stage was holistic (or exhaustive with K 0)
    first = p.get('prefilter', 'holistic' if prefiltered else 'exhaustive')
    if p.get('command'):
        lines += ['Regenerate with:', '', '```bash', p['command'], '```', '']
    lines += [
        'Percentages of the queries that have a true match; P@100%R = precision when every query is '
        "answered (= top-1 accuracy, the paper's headline), R@100%P = largest recall at precision 1, "
        'AUC-PR = area under the precision-recall curve of a threshold on the top-1 score. '
        + {
            'holistic': 'Every local method reranks the same holistic top-K.',
            'landmarks': 'Every local method reranks the top-K of the landmark first stage, run on its own '
            'landmarks (prefilter landmarks).',
            'exhaustive': 'Every local method scores every reference (exhaustive, no first stage).',
        }[first],
        '',
    ]
    for name, d in results['datasets'].items():
        lines += [f'## {name}', '']
        facts = [
            f'{d["queries"]} queries ({d.get("queries_with_match", "?")} with a true match), '
            f'{d.get("refs", "?")} references; {d.get("protocol", "")}'
        ]
        if d.get('spec'):
            facts.append(f'spec `{d["spec"]}`')
        info = {k: v for k, v in d.get('info', {}).items() if v not in (None, [], {})}
        if info:
            facts.append('; '.join(f'{k} {v}' for k, v in info.items()))
        if d.get('grid'):
            facts.append(f'feature grid {d["grid"][1]}x{d["grid"][0]} (cols x rows) of the first query')
        lines += ['; '.join(facts) + '.', '']
        lines += [f'Note: {n}.' for n in d.get('notes') or []] + [''] * bool(d.get('notes'))
        lines += [
            '| method | this data | n | P@100%R | R@100%P | AUC-PR | R@1 | R@5 | R@10 | extract ms/img | '
            'match ms/pair |',
            '|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|',
        ]
        best = max((m['p_at_100r'] for m in d['methods'].values() if m['p_at_100r'] is not None), default=None)
        for row, m in d['methods'].items():
            p100 = pct(m['p_at_100r'])
            if best is not None and m['p_at_100r'] == best:
                p100 = f'**{p100}**'
            label = row
            if row.startswith('lln') and not m.get('head_trained', True) and 'untrained' not in row:
                label += ' (untrained head)'
            lines.append(
                f'| {label} | {seen_by(d["methods"], row)} | {m["n"]} | {p100} | {pct(m["r_at_100p"])} | '
                f'{pct(m["auc_pr"])} | '
                f'{pct(m["r_at_1"])} | {pct(m["r_at_5"])} | {pct(m["r_at_10"])} | '
                f'{ms(m["extract_ms"])} | {ms(m["match_ms_per_pair"])} |'
            )
        lines += [
            '',
            "`this data`: whether the row's head trained on this dataset's images (`trained on`), "
            'validated on them (`validated on`: validation picks the kept epoch) or never saw them '
            "(`held out`); `-`: the row has no learned part (the backbone is ImageNet's).",
        ]
        curve = d.get('recall_at_k_holistic') or []
        k = p.get('prefilter_k')
        if curve and k == 0:
            lines += [
                '',
                'Exhaustive (prefilter_k 0): every reference is scored, so the holistic ranking '
                f'caps nothing (holistic recall@30 = {pct(curve[min(30, len(curve)) - 1])}% for comparison).',
            ]
        elif curve and k and first == 'holistic':
            at = curve[min(k, len(curve)) - 1]
            lines += [
                '',
                f'Holistic recall@{min(k, len(curve))} = {pct(at)}%: the ceiling of every reranking '
                'method (a true match outside the holistic top-K cannot be recovered).',
            ]
        stages = d.get('first_stage') or {}
        if stages:
            ks = [kk for kk in (1, 5, 10, 30, 100) if any(str(kk) in st['recall_at'] for st in stages.values())]
            lines += [
                '',
                'First stage (lln landmarks): recall@K of its own ranking = the ceiling of a rerank of '
                'its top K, and its cost per query.',
                '',
                '| first stage | ' + ' | '.join(f'R@{kk}' for kk in ks) + ' | ms/query |',
                '|---|' + '---:|' * (len(ks) + 1),
            ]
            for stage, st in stages.items():
                lines.append(
                    f'| {stage} | '
                    + ' | '.join(pct(st['recall_at'].get(str(kk))) for kk in ks)
                    + f' | {ms(st.get("ms_per_query"))} |'
                )
        t = d.get('timing', {})
        if t:
            lines += [
                '',
                f'Timing: extraction median over {t.get("images")} images, matching median over '
                f'{t.get("queries")} queries (each the best of {p.get("timing_repeats", 1)} runs), '
                f'CPU, {t.get("torch_threads")} torch threads.',
            ]
        if d.get('reloc'):
            lines += [''] + reloc_markdown(d['reloc'])
        figs = d.get('figures') or {}
        if figs:
            lines += ['']
            for key in ('pr', 'recall_at_k', 'heatmaps'):
                if figs.get(key):
                    lines.append(f'![{name} {key}]({figs[key]})')
            for ex in figs.get('examples', []):
                lines.append(
                    f'- {ex["kind"]}: [{ex["file"]}]({ex["file"]}) {ex["caption"]}'
                    + (
                        f' — against its true match: [{ex["truth_file"]}]({ex["truth_file"]})'
                        if ex.get('truth_file')
                        else ''
                    )
                )
        lines.append('')
    if p:
        lines += ['## Parameters', '']
        for key in (
            'backbone',
            'layer',
            'descriptor_space',
            'input_height',
            'top_n',
            'prefilter',
            'prefilter_k',
            'sequence_prefilter_k',
            'sequence_acquire_k',
            'scale',
            'rand_seed',
            'act_fusion',
            'timing_images',
            'timing_queries',
            'timing_repeats',
            'torch_threads',
            'blas_threads',
            'feature_cache',
            'sequence',
            'sequence_carry',
            'sequence_score_norm',
            'sequence_search',
            'seqslam',
        ):
            if key in p:
                lines.append(f'- {key}: `{p[key]}`')
        for label, h in p.get('heads', {}).items():
            lines.append(
                f'- head `{label}`: weights `{shown_path(h["weights"]) or "(Xavier init, seed 0)"}`, '
                f'trained {h["trained"]}, fingerprint `{h["fingerprint"]}`'
                + (f', trained on `{h["train_data"]}`' if h.get('train_data') else '')
                + (f', validated on `{", ".join(h["val_data"])}`' if h.get('val_data') else '')
                + (f', epoch {h["epoch"]} kept' if h.get('epoch') is not None and h.get('trained') else '')
            )
        lines += [
            '',
            'Rows: `holistic` = global max-pool descriptor ranking, no rerank, n = 1 (one vector per '
            'image); `lln`/`lln[X]` = top-n cells by the activation of LLN head X; `act` = top-n by '
            'feature norm; `rand` = the same n random cells in every image; `all` = every cell '
            '(n = median cells per image); `sad` = mean absolute difference of patch-normalised thumbnails, '
            "`seqslam` = the same, contrast-enhanced, with the sequence search; `X+seq` = row X's "
            'single-frame scores through the causal sequence search (the last L queries, '
            'constant velocity in the given range). Only the lln rows use a head. `extract ms/img` = full '
            'extraction from the original image (resize, backbone, head, selection; holistic: no '
            "head); `match ms/pair` = one query's rerank divided by its candidates (holistic: "
            'dot products with every reference). Features are cached as float16.',
            '',
        ]
    return '\n'.join(lines) + '\n'


def write_markdown(results: dict, path) -> None:
    Path(path).write_text(markdown(jsonable(results)))


def reloc_markdown(entry: dict) -> list[str]:
    """Markdown lines of one dataset's relocalization entry (evaluate_reloc)."""
    fast = f' FAST threshold {entry["fast_threshold"]}' if entry.get('fast_threshold') is not None else ''
    lines = [
        f'Relocalization ({entry["detector"]}{fast}, top-{entry["top"]} pLLN candidates, success = the best true '
        f'candidate reaches {entry["min_inliers"]} RANSAC inliers (F); {entry["queries"]} queries, a true '
        f'match in the top {entry["top"]} for {pct(entry["true_match_in_top"])}%; median '
        f'{num1(entry["keypoints_median"])} keypoints per image ({entry["keypoints_zero"]} images with none), '
        f'detection {num1(entry["detect_ms"])} ms/img; regions grown by {entry["margin"]:g} cells):',
        '',
        '| keypoint matching | success % | mean inliers (best true) | mean inliers (false) | matches/pair | ms/query |',
        '|---|---:|---:|---:|---:|---:|',
    ]
    for name, label in (('regions', 'mLLN (matched regions)'), ('all', 'all keypoints')):
        m = entry[name]
        lines.append(
            f'| {label} | {pct(m["success_rate"])} | {num1(m["mean_inliers_true"])} | '
            f'{num1(m["mean_inliers_false"])} | {num1(m["matches_per_pair"])} | {num1(m["ms_per_query"])} |'
        )
    return lines


# -------------------------------------------------------------------------------- lln-demo (online)


def table(online: dict, offline: dict | None, comparison: dict | None, as_markdown: bool = False) -> str:
    head = ['metric (%)', 'online'] + (['offline', 'online − offline'] if offline else [])
    rows = []
    for key, label in METRICS:
        row = [label, pct(online['summary'][key])]
        if offline:
            d = comparison['metric_diff'][key]
            row += [pct(offline['summary'][key]), '–' if d is None else f'{100 * d:+.1f}']
        rows.append(row)
    q = len(online['ranked'])
    row = ['queries answered', f'{online["answered"]}/{q}']
    if offline:
        row += [f'{int((offline["ranked"][:, 0] >= 0).sum())}/{q}', '']
    rows.append(row)
    if offline:
        rows.append(['same top-1', f'{comparison["same_top1"]}/{q}', '', ''])
    if as_markdown:
        lines = ['| ' + ' | '.join(head) + ' |', '|' + '|'.join(['---'] + ['---:'] * (len(head) - 1)) + '|']
        lines += ['| ' + ' | '.join(r) + ' |' for r in rows]
        return '\n'.join(lines)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]

    def fmt(r):
        return '  '.join(c.ljust(widths[0]) if i == 0 else c.rjust(widths[i]) for i, c in enumerate(r))

    return '\n'.join([fmt(head), '  '.join('-' * w for w in widths)] + [fmt(r) for r in rows])


def transport_lines(tr: dict) -> list[str]:
    m, q = tr['map'], tr['query']

    def again(t):
        if not t.get('resent'):
            return ''
        return (
            f' (+{t["resent"]} first frame sent again: it was published before the '
            'extractor and the matcher had matched)'
        )

    dup = f', {m["duplicate_keyframes"]} DUPLICATES' if m.get('duplicate_keyframes') else ''
    return [
        f'map:   {m["frames"]} frames played{again(m)}; extractor received {m["extractor_received"]}, published '
        f'{m["extractor_published"]}, dropped {m["extractor_dropped"]}; landmarks seen {m["landmarks_seen"]}; '
        f'keyframes stored {m["keyframes_in_map_file"]} (refused {m["bad_keyframe"]}{dup})',
        f'query: {q["frames"]} frames played{again(q)}; extractor received {q["extractor_received"]}, published '
        f'{q["extractor_published"]}, dropped {q["extractor_dropped"]}; answered {q["answered"]} '
        f'(refused {q["bad_query"]})',
        f'lost in transport: {m["lost"]} map frames, {q["lost"]} queries',
    ]


def online_console(online: dict, offline: dict | None, comparison: dict | None) -> str:
    """What lln-demo prints at the end: the table, the transport lines, the agreement and its causes."""
    lines = [table(online, offline, comparison), *transport_lines(online['transport'])]
    if comparison is not None:
        lines.append(
            ('online and offline AGREE on every metric' if comparison['agree'] else 'online and offline DIFFER')
            + ''.join(f'\n  - {n}' for n in comparison['notes'])
        )
        lines += [
            f'    query {c["query"]}: online top-1 ref {c["online"]}, offline ref {c["offline"]}: '
            f'{c["cause"]}: {c["detail"]}'
            for c in comparison['differing_queries'][:10]
        ]
    return '\n'.join(lines)


def online_markdown(report: dict, online: dict, offline: dict | None, comparison: dict | None) -> str:
    d, p, tr, t = report['dataset'], report['parameters'], report['transport'], report['timing_s']
    lines = [
        '# lln-demo results',
        '',
        'Regenerate with:',
        '',
        '```bash',
        report['command'],
        '```',
        '',
        f'Dataset **{d["name"]}** (`{d["spec"]}`{", range " + d["range"] if d.get("range") else ""}): '
        f'{d["refs"]} map frames (keyframes), {d["queries"]} queries ({d["queries_with_match"]} with a '
        f'true match).',
        '',
        f'Through the nodes ({p["executables"]}): two extractors (method `{p["method"]}`, top-n '
        f'{p["top_n"]}, reliable image QoS) and the matcher in localization mode (prefilter '
        f'{p.get("prefilter", "holistic")}, prefilter_k {p["prefilter_k"]}, k {p["k"]}), '
        f'ROS_DOMAIN_ID {p["domain_id"]} on localhost; playback '
        f'{p["playback"]}.',
        '',
        table(online, offline, comparison, as_markdown=True),
        '',
    ]
    if comparison:
        lines += [
            (
                '**Online and offline agree on every metric.**'
                if comparison['agree']
                else '**Online and offline differ.**'
            )
            + ' '
            + ' '.join(n + '.' for n in comparison['notes']),
            '',
        ]
        if comparison['differing_queries']:
            lines += ['| query | online top-1 | offline top-1 | cause | detail |', '|---:|---:|---:|---|---|']
            lines += [
                f'| {c["query"]} | {c["online"]} | {c["offline"]} | {c["cause"]} | {c["detail"]} |'
                for c in comparison['differing_queries'][:30]
            ]
            lines += ['']
        if comparison['score_rel_diff_median'] is not None:
            lines += [
                f'Top-1 score, online vs offline, where the top-1 agrees: median relative difference '
                f'{comparison["score_rel_diff_median"]:.2e}, max {comparison["score_rel_diff_max"]:.2e}.',
                '',
            ]
    lines += ['## Transport', ''] + [f'- {line}' for line in transport_lines(tr)] + ['']
    lines += ['## Timing', '', '| step | seconds |', '|---|---:|']
    lines += [f'| {k} | {v:.1f} |' for k, v in t.items() if v is not None]
    lines += ['']
    figs = report['figures']
    lines += ['## Figures', '', f'![PR curve]({figs["pr"]})', '']
    for ex in figs['examples']:
        lines.append(
            f'- {ex["kind"]}: [{ex["file"]}]({ex["file"]}) query {ex["query"]} -> ref {ex["answer"]}, '
            f'S = {ex["score"]:.2f}, {ex["pairs"]} matched regions'
        )
    if offline:
        lines += ['', 'Offline results and figures: [offline/results.md](offline/results.md).']
    return '\n'.join(lines) + '\n'


def write_answers(ds, run: dict, online: dict, offline: dict | None, path: Path) -> None:
    correct = metrics.top1_correct(online['ranked'], ds.gt)
    with open(path, 'w', newline='') as f:
        w = csv.writer(f)
        w.writerow(
            [
                'query',
                'query_file',
                'stamp_ns',
                'top1_ref',
                'top1_file',
                'score',
                'holistic_score',
                'correct',
                'true_refs',
            ]
            + (['offline_top1_ref', 'offline_score'] if offline else [])
        )
        for q, path_q in enumerate(ds.query_paths):
            r = int(online['ranked'][q, 0])
            truth = ' '.join(map(str, np.flatnonzero(ds.gt[q])[:10]))
            row = [
                q,
                Path(path_q).name,
                run['query_stamps'][q],
                r if r >= 0 else '',
                Path(ds.ref_paths[r]).name if r >= 0 else '',
                f'{online["scores"][q, 0]:.6g}' if r >= 0 else '',
                f'{online["holistic"][q, 0]:.6g}' if r >= 0 else '',
                int(correct[q]),
                truth,
            ]
            if offline:
                ro = int(offline['ranked'][q, 0])
                row += [ro if ro >= 0 else '', f'{offline["scores"][q, 0]:.6g}' if ro >= 0 else '']
            w.writerow(row)
