"""The figures of lln-eval and lln-demo: PR curves (the paper's Fig. 5), holistic recall@K (Fig. 4),
score-map heatmaps (Fig. 3) and match pictures of successes and failures (Fig. 7).

Legends print every metric as a percentage (report.pct), as the tables do; PR legends sit below
the axes, so they never hide the ends of the curves.

Which match pictures (pick_examples): the route (query order) is cut into as many equal stretches
as pictures are asked for, and each stretch gives its most confident success (failure) whose query
frame shows something: grey mean >= DARK_MEAN and grey std >= FLAT_STD. Nordland's winter traverse
has ~10% near-black or flat frames (tunnels, night); ranked by score alone they filled the pictures.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core import metrics
from ..core.landmark_index import check_prefilter
from ..core.landmarks import METHODS as LOCAL_METHODS
from ..core.landmarks import stack_landmarks
from ..core.similarity import match_batch, match_pair
from .methods import parse_methods, row_names, slug, variant
from .peers import PEER_METHODS
from .report import pct


def _pyplot():
    import matplotlib.pyplot as plt

    from ..viz import plotting  # noqa: F401  (selects the Agg backend first: files only, no display)

    return plt


SEQ = '+seq'  # the suffix of lln-eval's sequence-search rows


def _line(row: str, single: str) -> str:
    """The line style of a row: `single` for a single-frame row, dash-dot for its X+seq row."""
    return '-.' if row.endswith(SEQ) else single


def _colours(rows: list[str]) -> dict:
    """A colour per row, distinct per method; X+seq shares X's."""
    plt = _pyplot()
    fixed = {
        'holistic': 'tab:gray',
        'act': 'tab:green',
        'rand': 'tab:orange',
        'all': 'tab:purple',
        'sad': 'black',
        'seqslam': 'tab:olive',
    }
    lln_cols = iter(['tab:blue', 'tab:red', 'tab:cyan', 'tab:brown', 'tab:pink'])
    out = {}
    for r in rows:
        base = r.removesuffix(SEQ)  # X+seq is drawn in X's colour (and dash-dotted, _line)
        if base not in out:
            out[base] = fixed.get(base) or next(lln_cols, None) or plt.get_cmap('tab20')(len(out) % 20)
        out[r] = out[base]
    return out


DARK_MEAN = 40.0  # grey-level mean below which a frame is too dark to teach anything
FLAT_STD = 12.0  # grey-level standard deviation below which it is too flat (fog, a wall, motion blur)


def informative(path) -> bool:
    """Whether an image file is worth showing: neither near-black nor flat (DARK_MEAN, FLAT_STD)."""
    import cv2

    grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    return grey is not None and float(grey.mean()) >= DARK_MEAN and float(grey.std()) >= FLAT_STD


def nearest_informative(paths: list, i: int, reach: int = 50) -> int:
    """The index nearest to i (within reach) whose image is informative(); i itself when none is."""
    for d in range(reach + 1):
        for j in (i - d, i + d):
            if 0 <= j < len(paths) and informative(paths[j]):
                return j
    return i


def pick_examples(ranked: np.ndarray, scores: np.ndarray, gt: np.ndarray, query_paths: list, count: int) -> dict:
    """{'success': [q, ...], 'failure': [q, ...]}: per kind, the route cut into `count` stretches
    of queries and the most confident query of that kind in each whose frame is informative(); a
    stretch without one is made up from the others (still informative ones first). ranked,
    scores: (Q, K); gt: (Q, R) bool. Failures are answered queries with a true match elsewhere."""
    correct = metrics.top1_correct(ranked, gt)
    answered = ranked[:, 0] >= 0
    conf = np.nan_to_num(scores[:, 0].astype(np.float64), nan=-1e30, neginf=-1e30)
    kinds = {'success': correct, 'failure': answered & gt.any(1) & ~correct}
    seen: dict = {}

    def shows(q: int) -> bool:
        if q not in seen:
            seen[q] = informative(query_paths[q])
        return seen[q]

    out = {}
    for kind, mask in kinds.items():
        chosen: list[int] = []
        if count > 0 and mask.any():
            bounds = np.linspace(0, len(ranked), count + 1).astype(int)
            for a, b in zip(bounds[:-1], bounds[1:]):
                stretch = [int(a) + int(i) for i in np.argsort(-conf[a:b], kind='stable') if mask[a + int(i)]]
                q = next((q for q in stretch if shows(q)), None)
                if q is not None:
                    chosen.append(q)
            rest = [int(q) for q in np.argsort(-conf, kind='stable') if mask[q] and int(q) not in chosen]
            for q in [q for q in rest if shows(q)] + [q for q in rest if not shows(q)]:
                if len(chosen) >= count:
                    break
                chosen.append(q)
        out[kind] = sorted(chosen[:count])  # route order
    return out


def curve_label(name: str, summary: dict) -> str:
    """The legend entry of one PR curve: the same numbers, in the same unit, as the tables."""
    return f'{name}: P@100%R {pct(summary.get("p_at_100r"))}%, AUC-PR {pct(summary.get("auc_pr"))}%'


def plot_pr(curves: list[tuple], gt: np.ndarray, path, title: str) -> None:
    """PR curves on one plot (threshold on the top-1 score). curves: (label, ranked (Q, K),
    scores (Q, K), summary (metrics.summary keys), line style, colour); X+seq rows dash-dotted in X's colour."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 5.2 + 0.22 * len(curves)), dpi=110)
    for label, ranked, scores, summary, style, colour in curves:
        prec, rec, _ = metrics.pr_curve(ranked, scores[:, 0], gt)
        ax.plot(
            np.r_[0.0, rec],
            np.r_[prec[:1] if len(prec) else [1.0], prec],
            style,
            color=colour,
            lw=1.6,
            label=curve_label(label, summary),
        )
    ax.set_xlim(0, 1.01)
    ax.set_ylim(0, 1.02)
    ax.set_xlabel('recall')
    ax.set_ylabel('precision')
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=9)
    # below the axes: a legend inside would sit on the curves' ends (they finish at low precision
    # bottom right, or start at the top left)
    ax.legend(fontsize=7 if len(curves) > 3 else 8, loc='upper left', bbox_to_anchor=(0.0, -0.12), frameon=False)
    fig.tight_layout()
    fig.savefig(path, bbox_inches='tight')
    plt.close(fig)


def rows_curves(run) -> list[tuple]:
    """plot_pr curves of every row of an lln-eval DatasetRun (holistic dashed)."""
    colours = _colours(list(run.rankings))
    return [
        (row, ranked, scores, run.entry['methods'][row], _line(row, '--' if row == 'holistic' else '-'), colours[row])
        for row, (ranked, scores) in run.rankings.items()
    ]


def online_curves(online: dict, offline: dict | None) -> list[tuple]:
    """plot_pr curves of lln-demo: the nodes' answers and, when run, the offline evaluator's."""
    curves = [('online (nodes)', online['ranked'], online['scores'], online['summary'], '-', 'tab:blue')]
    if offline:
        curves.append(
            ('offline (lln-eval)', offline['ranked'], offline['scores'], offline['summary'], '--', 'tab:orange')
        )
    return curves


def _recall_label(row: str, k: int) -> str:
    """What a recall@K curve ranks: a rerank of the first stage's top k, or every reference (the
    whole-image peers sad and seqslam, and holistic+seq, whose sequence search sees every one)."""
    method = row.removesuffix(SEQ)
    if method in PEER_METHODS or method == 'holistic':
        return f'{row} ({"sequence search" if row != "sad" else "whole image"}, every reference)'
    if row.endswith(SEQ):
        return f"{row} (sequence search over {method}'s reranked list)"
    return f'{row} (its first-stage top-{k}, reranked)'


def plot_recall_at_k(run, gt: np.ndarray, prefilter_k: int, path) -> None:
    """Holistic recall@K against K (the paper's Fig. 4), reranked methods within the top-K dashed
    (X+seq dash-dotted, in X's colour). The legend sits below the axes, as plot_pr's."""
    plt = _pyplot()
    colours = _colours(list(run.rankings))
    fig, ax = plt.subplots(figsize=(7.2, 6.4), dpi=110)
    ks = np.arange(1, len(run.recall_curve) + 1)
    ax.plot(
        ks,
        run.recall_curve,
        '-o',
        ms=2.5,
        color=colours.get('holistic', 'tab:gray'),
        label='holistic (global descriptor ranking)',
    )
    for row, (ranked, _) in run.rankings.items():
        if row == 'holistic':
            continue
        kk = np.arange(1, min(ranked.shape[1], len(run.recall_curve)) + 1)
        ax.plot(
            kk,
            [metrics.recall_at_k(ranked, gt, int(k)) for k in kk],
            _line(row, '--'),
            lw=1,
            color=colours[row],
            label=_recall_label(row, ranked.shape[1]),
        )
    if prefilter_k:  # 0: exhaustive, no cut-off to mark
        ax.axvline(prefilter_k, color='k', lw=0.8, ls=':', label=f'K = {prefilter_k}: candidates reranked')
    ax.set_ylim(0, 1.02)
    ax.set_xlabel('K (candidates)')
    ax.set_ylabel('recall@K')
    ax.grid(alpha=0.3)
    ax.set_title(f'{run.name}: a true match among the top K', fontsize=9)
    ax.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    fig.tight_layout()
    fig.savefig(path, bbox_inches='tight')
    plt.close(fig)


def plot_heatmaps(
    images: list[np.ndarray],
    rows: list[tuple[str, list, list]],
    path,
    title: str = '',
    columns: list[str] | None = None,
) -> None:
    """Grid of images (columns) x selectors (rows): score-map heatmap and the selected cells outlined
    (the paper's Fig. 3). rows: (label, score maps (rows, cols) per image, LandmarkSets per image);
    columns: a title per image (e.g. 'query 12'). A colour bar gives the heatmap's scale and a
    legend the outlined cells."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.patches import Patch, Rectangle

    from ..io.image import heatmap
    from ..viz.plotting import ACTIVATION_CMAP

    plt = _pyplot()
    nr, nc = len(rows), len(images)
    fig, axes = plt.subplots(nr, nc, figsize=(3.2 * nc + 1.0, 2.6 * nr + 1.0), dpi=100, squeeze=False)
    for r, (label, maps, sets) in enumerate(rows):
        for c, img in enumerate(images):
            ax = axes[r][c]
            ax.imshow(img)
            heat = heatmap(maps[c], (img.shape[1], img.shape[0]))
            ax.imshow(heat, cmap=ACTIVATION_CMAP, alpha=0.55 * heat)
            s = sets[c]
            for u, v in s.centers:
                w, h = s.cell_size
                ax.add_patch(Rectangle((u - w / 2, v - h / 2), w, h, fill=False, lw=0.8, ec='white'))
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
            if r == 0 and columns:
                ax.set_title(columns[c], fontsize=8)
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout(rect=(0, 0.07, 0.93, 1))
    bar = fig.add_axes((0.94, 0.15, 0.012, 0.7))
    fig.colorbar(
        ScalarMappable(Normalize(0, 1), ACTIVATION_CMAP), cax=bar, label='score, 0 .. max of each image (0 = no tint)'
    )
    fig.legend(
        handles=[Patch(fill=False, ec='grey', lw=0.8, label='a selected cell (a landmark of that row)')],
        loc='lower center',
        fontsize=8,
        frameon=False,
    )
    fig.savefig(path)
    plt.close(fig)


def write_figures(
    run, ds, extractor, heads: list, conf: dict, feats: dict, ref_sizes: list, query_sizes: list, out: Path
) -> dict:
    """PNGs of one dataset; returns {'pr', 'recall_at_k', 'heatmaps': file, 'examples': [...]}."""
    from ..io.image import load_image
    from ..viz.plotting import plot_matches

    stem = slug(run.name)
    figs: dict = {}
    figs['pr'] = f'{stem}_pr.png'
    plot_pr(rows_curves(run), ds.gt, out / figs['pr'], f'{run.name}: precision-recall (threshold on the top-1 score)')
    figs['recall_at_k'] = f'{stem}_recall_at_k.png'
    plot_recall_at_k(run, ds.gt, int(conf['prefilter_k']), out / figs['recall_at_k'])
    top_n, scale = int(conf['top_n']), float(conf['scale'])
    methods = parse_methods(conf['methods'])
    qfeat = lambda i: feats[str(ds.query_paths[i])]  # noqa: E731
    rfeat = lambda i: feats[str(ds.ref_paths[i])]  # noqa: E731

    count = min(int(conf['heatmap_images']), len(ds.query_paths))
    if count:
        # evenly along the route, each moved to the nearest informative frame (not a dark / flat one)
        along = np.linspace(0, len(ds.query_paths) - 1, count).astype(int)
        idx = np.unique([nearest_informative(ds.query_paths, int(i)) for i in along])
        images = [load_image(str(ds.query_paths[i])) for i in idx]
        rows = []
        show = heads if 'lln' in methods or len(heads) > 1 else heads[:1]
        for h in show:
            v = variant(extractor, 'lln', top_n, h)
            sets = [v.from_features(qfeat(i), query_sizes[i]) for i in idx]
            label = f'LLN {h.label}'.strip() + ('' if h.trained else ' (untrained)')
            rows.append((label, [s.activation for s in sets], sets))
        if 'act' in methods:
            v = variant(extractor, 'act', top_n)
            sets = [v.from_features(qfeat(i), query_sizes[i]) for i in idx]
            norms = [np.linalg.norm(np.asarray(qfeat(i), np.float32), axis=0) for i in idx]
            rows.append(('ACT (feature norm)', norms, sets))
        figs['heatmaps'] = f'{stem}_heatmaps.png'
        plot_heatmaps(
            images,
            rows,
            out / figs['heatmaps'],
            f'{run.name}: where each selector puts its top-{top_n} landmarks (query frames along the route)',
            columns=[f'query {i}' for i in idx],
        )

    # match pictures: the first lln row (else the first local row), confident successes and failures
    local = [(r, m, h) for r, m, h in row_names(methods, heads) if m in LOCAL_METHODS]
    figs['examples'] = []
    if not local or int(conf['examples']) <= 0:
        return figs
    row, method, head = local[0]
    v = variant(extractor, method, top_n, head if method == 'lln' else None)
    ranked, scores = run.rankings[row]
    picked = pick_examples(ranked, scores, ds.gt, ds.query_paths, int(conf['examples']))
    k = ranked.shape[1]
    # the holistic rank decides candidacy only when the holistic top-k was the first stage
    holistic_first = check_prefilter(conf['prefilter'], int(conf['prefilter_k']))[0] == 'holistic'
    for kind, queries in picked.items():
        for j, q in enumerate(queries, 1):
            r = int(ranked[q, 0])
            qs = v.from_features(qfeat(q), query_sizes[q])
            rs = v.from_features(rfeat(r), ref_sizes[r])
            res = match_pair(qs, rs, scale)
            qimg, rimg = load_image(str(ds.query_paths[q])), load_image(str(ds.ref_paths[r]))
            name = f'{stem}_{slug(row)}_{kind}{j}_q{q}.png'
            truth = np.flatnonzero(ds.gt[q])
            hol_rank = (
                int(np.flatnonzero(np.isin(run.holistic_full[q], truth))[0]) + 1
                if np.isin(run.holistic_full[q], truth).any()
                else None
            )
            verdict = 'correct' if kind == 'success' else f'WRONG (true: {", ".join(map(str, truth[:5]))})'
            line1 = f'query {q} ({Path(ds.query_paths[q]).name}) -> ref {r} ({Path(ds.ref_paths[r]).name}), {verdict}'
            line2 = (
                f'S = {scores[q, 0]:.2f}, {len(res.pairs(0)["weight"])} mutual pairs; first true match at '
                f'holistic rank {hol_rank}'
                + (
                    f' (outside the top-{k}: no rerank can recover it)'
                    if holistic_first and hol_rank and hol_rank > k
                    else ''
                )
            )
            caption = f'{line1}, {line2}'
            plot_matches(
                qimg,
                rimg,
                qs,
                rs,
                res.pairs(0),
                str(out / name),
                title=f'{run.name} {row}: {line1}\n{line2}',
                labels=(f'query {q}', f'map: ref {r}, the answer ({"right" if kind == "success" else "WRONG"})'),
            )
            ex = {
                'kind': kind,
                'file': name,
                'query': int(q),
                'answer': int(r),
                'score': float(scores[q, 0]),
                'caption': caption,
            }
            if kind == 'failure' and len(truth):
                true_sets = [v.from_features(rfeat(int(t)), ref_sizes[int(t)]) for t in truth]
                tres = match_batch(qs, stack_landmarks(true_sets), scale)
                b = int(np.argmax(tres.scores))
                t = int(truth[b])
                tname = f'{stem}_{slug(row)}_{kind}{j}_q{q}_truth.png'
                plot_matches(
                    qimg,
                    load_image(str(ds.ref_paths[t])),
                    qs,
                    true_sets[b],
                    tres.pairs(b),
                    str(out / tname),
                    title=f'{run.name} {row}: query {q} vs its true match ref {t}\n'
                    f'S = {tres.scores[b]:.2f} (the wrong answer ref {r} scored '
                    f'{scores[q, 0]:.2f})',
                    labels=(f'query {q}', f'map: ref {t}, the true match (not the answer)'),
                )
                ex['truth_file'] = tname
                ex['truth'] = t
            figs['examples'].append(ex)
    return figs


def figure_files(figs: dict | None) -> list[str]:
    if not figs:
        return []
    out = [f for key, f in figs.items() if key != 'examples' and f]
    for ex in figs.get('examples', []):
        out += [ex['file']] + ([ex['truth_file']] if ex.get('truth_file') else [])
    return out


def plot_online_examples(ds, run: dict, online: dict, out: Path, count: int) -> list[dict]:
    """Query / keyframe pictures with the `matches` regions of the best candidate drawn (the
    landmarks outlined come from the extractors' clouds): successes and failures across the route (pick_examples)."""
    from types import SimpleNamespace

    from ..io.image import load_image
    from ..viz.plotting import plot_matches

    if count <= 0:
        return []
    ranked, scores = online['ranked'], online['scores']
    picked = pick_examples(ranked, scores, ds.gt, ds.query_paths, count)
    out_list = []
    for kind, queries in picked.items():
        for j, q in enumerate(queries, 1):
            r = int(ranked[q, 0])
            qstamp, rstamp = run['query_stamps'][q], run['ref_stamps'][r]
            m = run['matches'].get(qstamp)
            if m is None:
                continue
            qc, qcell = run['landmarks']['query'].get(qstamp, (None, None))
            rc, rcell = run['landmarks']['keyframes'].get(rstamp, (None, None))
            qpts = np.stack([m['query_u'], m['query_v']], 1).astype(np.float32)
            rpts = np.stack([m['map_u'], m['map_v']], 1).astype(np.float32)
            if qc is None:
                qc, qcell = qpts, (float(m['cell_w'][0]) if len(m) else 1.0, float(m['cell_h'][0]) if len(m) else 1.0)
            if rc is None:
                rc, rcell = rpts, (float(m['cell_w'][0]) if len(m) else 1.0, float(m['cell_h'][0]) if len(m) else 1.0)

            def index_of(points, centers):
                if not len(points):
                    return np.zeros(0, np.int64)
                d = ((points[:, None, :] - centers[None, :, :]) ** 2).sum(-1)
                return d.argmin(1)

            pairs = {
                'query_index': index_of(qpts, qc),
                'map_index': index_of(rpts, rc),
                'similarity': np.asarray(m['similarity'], np.float32),
                'weight': np.asarray(m['weight'], np.float32),
            }
            qset = SimpleNamespace(centers=qc, cell_size=np.array(qcell, np.float32), activation=None)
            rset = SimpleNamespace(centers=rc, cell_size=np.array(rcell, np.float32), activation=None)
            truth = np.flatnonzero(ds.gt[q])
            verdict = 'correct' if kind == 'success' else f'WRONG (true: {", ".join(map(str, truth[:5]))})'
            title = (
                f'online: query {q} ({Path(ds.query_paths[q]).name}) -> keyframe of ref {r} '
                f'({Path(ds.ref_paths[r]).name}), {verdict}\nS = {scores[q, 0]:.2f}, {len(m)} matched region '
                f'pairs from /matches'
            )
            name = f'matches_online_{kind}{j}_q{q}.png'
            plot_matches(
                load_image(str(ds.query_paths[q])),
                load_image(str(ds.ref_paths[r])),
                qset,
                rset,
                pairs,
                str(out / name),
                title=title,
                labels=(
                    f'query {q}',
                    f'map: keyframe of ref {r}, the answer ({"right" if kind == "success" else "WRONG"})',
                ),
            )
            out_list.append(
                {
                    'kind': kind,
                    'file': name,
                    'query': q,
                    'answer': r,
                    'score': float(scores[q, 0]),
                    'pairs': int(len(m)),
                }
            )
    return out_list
