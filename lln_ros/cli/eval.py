"""lln-eval: every place-recognition method on every dataset, with the paper's protocol and pictures.

    lln-eval --dataset SPEC [--dataset SPEC ...] --out DIR [--methods holistic,lln,act,rand,all]
             [--top-n 50] [--prefilter landmarks|holistic|exhaustive] [--prefilter-k 30|0]
             [--range START:END] [--sequence L [--sequence-prefilter-k 30] [--sequence-carry 10]
             [--sequence-score-norm none|zscore]]
             [--weights [LABEL=]CKPT ...] [--label NAME ...] [--heads LABEL=CKPT,LABEL=,...]
             [--backbone NAME] [--layer LAYER] [--cache DIR] [--download [--download-url URL]]

SPEC: vprbench:DIR | aligned:DIR_REF,DIR_QUERY[,TOL] | loop:DIR,GT_FILE | gardenspoint:DIR[,REF,QUERY],
each optionally followed by ,KEY=VALUE options: sequence=0|1 (is it one route? default 1, vprbench 0;
sequence rows and seqslam are skipped with a note where it is 0) and, for aligned, drop=MODES (query
frames to drop: flat (the default), blank, frozen, '+'-joined, or none; Nordland: drop=blank+frozen).
--range START:END (fractions) selects that part of every `aligned:` dataset (e.g. 0.7:1 = the last 30%
of the route); other kinds are used whole. Each head named by --weights / --heads is its own row
`lln[LABEL]`: `--heads trained=best.pt,untrained=` compares a trained head with the untrained
(seeded Xavier) head in one run; `LABEL=CKPT@act_fusion=A` ranks that row's cells by the head's
logits fused with ACT's feature norm (extractor act_fusion, docs/generalisation.md).
An empty CKPT (or `xavier`) is the untrained head, `shipped` the head
shipped with the package; without any, the row `lln` uses the shipped head (untrained if none ships).
act / rand / all / holistic do not depend on the head and get one row each. The classic peers
`sad` and `seqslam` (SeqSLAM, Milford and Wyeth 2012) are methods too; --sequence L adds an `X+seq`
row per holistic/local row: its scores through the matcher's online sequence search (L queries),
local rows over the rerank of --sequence-prefilter-k first-stage candidates (the matcher's default).

--geometry (with --dataset poses:DIR, a TUM RGB-D folder with depth/ and camera_info.yaml) runs only the
metric loop-closure evaluation instead (lln_ros.eval.geometry, docs/geometry.md): the sequence through
extractor, localizer and core.geometry, thresholds chosen on one half and figures reported on the other,
written as the `geometry` object of DIR/results.json (other keys of an existing file are kept).

Every dataset is read and checked, and every head loaded, before any feature is computed. Bad input
exits 2 with one line on stderr. Writes DIR/results.json, DIR/results.md and PNGs.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

from .common import (
    UsageError,
    add_model_arguments,
    add_prefilter_argument,
    add_scale_argument,
    download_dataset,
    extractor_conf,
    parser_from_doc,
    progress_log,
    read_dataset,
    run_cli,
)

PROG = 'lln-eval'


def build_parser() -> argparse.ArgumentParser:
    from ..core.reloc import DETECTORS
    from ..core.sequence import SCORE_NORMS
    from ..eval.methods import ALL_METHODS, METHODS
    from ..eval.runner import default_conf as conf

    p = parser_from_doc(PROG, __doc__)
    p.add_argument('--dataset', action='append', required=True, metavar='SPEC', help='dataset (repeatable)')
    p.add_argument(
        '--methods',
        default=','.join(METHODS),
        help=f'comma-separated subset of {",".join(ALL_METHODS)} (default: {",".join(METHODS)})',
    )
    add_prefilter_argument(p, 'first-stage candidates every local method reranks')
    add_scale_argument(p)
    p.add_argument(
        '--similarity-center',
        action=argparse.BooleanOptionalAction,
        default=conf['similarity_center'],
        help='S on each landmark set minus its own mean (similarity.center_sets; docs/method.md)',
    )
    p.add_argument(
        '--similarity-whitening',
        action=argparse.BooleanOptionalAction,
        default=conf['similarity_whitening'],
        help="S on each landmark set centred, then whitened with the model's shipped whitening (docs/method.md)",
    )
    p.add_argument(
        '--similarity-fusion',
        action=argparse.BooleanOptionalAction,
        default=conf['similarity_fusion'],
        help="S = raw S + fusion_weight x whitened S, the pairs of raw S (similarity, center='fuse'; docs/method.md)",
    )
    p.add_argument(
        '--landmark-whitening',
        action=argparse.BooleanOptionalAction,
        default=conf['landmark_whitening'],
        help="the landmark first stage whitens with the model's shipped whitening (core.whitening; docs/method.md)",
    )
    p.add_argument(
        '--landmark-knn',
        type=int,
        default=conf['landmark_knn'],
        metavar='K',
        help='the landmark first stage: map landmarks each query landmark retrieves (landmark_knn)',
    )
    p.add_argument(
        '--landmark-alpha',
        type=float,
        default=conf['landmark_alpha'],
        metavar='A',
        help="the landmark first stage: a hit's vote exponent (landmark_alpha)",
    )
    p.add_argument(
        '--sequence',
        type=int,
        default=conf['sequence'],
        metavar='L',
        help='add an X+seq row per holistic/local method: sequence search over L queries '
        f'(0 = off; seqslam uses L, or {conf["seqslam_length"]})',
    )
    p.add_argument(
        '--sequence-prefilter-k',
        type=int,
        default=conf['sequence_prefilter_k'],
        metavar='K',
        help='first-stage candidates the X+seq rows of local methods rerank, at least --prefilter-k '
        f'(default {conf["sequence_prefilter_k"]}, as the matcher with sequence_length; 0 = every reference)',
    )
    p.add_argument(
        '--sequence-acquire-k',
        type=int,
        default=conf['sequence_acquire_k'],
        metavar='K',
        help='X+seq of local methods: first-stage candidates of the first L - 1 queries, while the window fills, '
        f"as the matcher's sequence_acquire_k (default {conf['sequence_acquire_k']}; 0 = --sequence-prefilter-k's)",
    )
    p.add_argument(
        '--sequence-carry',
        type=int,
        default=conf['sequence_carry'],
        metavar='N',
        help="X+seq of local methods: also score the previous query's N best sequence ends' next references, "
        "as the matcher's sequence_carry does (0 = off)",
    )
    p.add_argument(
        '--sequence-score-norm',
        choices=SCORE_NORMS,
        default=conf['sequence_score_norm'],
        help="X+seq rows: each query's raw scores in the line search (none, the matcher's default) or in standard "
        'deviations above its lowest candidate (zscore); seqslam keeps its own contrast enhancement',
    )
    p.add_argument('--out', required=True, metavar='DIR', help='output folder (results.json, results.md, PNGs)')
    p.add_argument('--range', help='START:END fractions of every aligned dataset (e.g. 0.7:1)')
    p.add_argument(
        '--weights',
        action='append',
        metavar='[LABEL=]CKPT',
        help='LLN head checkpoint, one lln row each (repeatable); empty or "xavier" = untrained',
    )
    p.add_argument(
        '--label',
        action='append',
        metavar='NAME',
        help='row label for the --weights given in the same position (repeatable)',
    )
    p.add_argument(
        '--heads',
        action='append',
        metavar='LABEL=CKPT[,LABEL=CKPT]',
        help='several labelled heads at once, e.g. trained=best.pt,untrained=',
    )
    add_model_arguments(p, weights=False)
    p.add_argument('--cache', default=conf['cache_dir'], help=f'backbone feature cache (default {conf["cache_dir"]})')
    p.add_argument(
        '--download',
        action='store_true',
        help='gardenspoint:DIR lacking its folders: fetch GardensPoint_Walking.zip into DIR',
    )
    p.add_argument('--download-url', default=None, help='where --download fetches from (default: the public archive)')
    p.add_argument(
        '--threads',
        type=int,
        default=0,
        help='extractor runtime threads, and numpy BLAS threads when run as a command (0 = defaults)',
    )
    p.add_argument(
        '--timing-images', type=int, default=conf['timing_images'], help='images per dataset extraction is timed on'
    )
    p.add_argument(
        '--timing-queries', type=int, default=conf['timing_queries'], help='queries per dataset matching is timed on'
    )
    p.add_argument(
        '--timing-repeats', type=int, default=conf['timing_repeats'], help='timing rounds; the best of them counts'
    )
    p.add_argument(
        '--examples', type=int, default=conf['examples'], help='success and failure match pictures per dataset'
    )
    p.add_argument(
        '--heatmap-images', type=int, default=conf['heatmap_images'], help='images in the heatmap figure (0 = none)'
    )
    p.add_argument('--no-plots', action='store_true', help='write results.json and results.md only')
    p.add_argument(
        '--reloc',
        action='store_true',
        help='also relocalization: top-5 lln candidates, region-constrained vs all-keypoint matching',
    )
    p.add_argument(
        '--reloc-min-inliers',
        type=int,
        default=conf['reloc_min_inliers'],
        help=f'inliers a true candidate needs (default {conf["reloc_min_inliers"]})',
    )
    p.add_argument(
        '--reloc-top',
        type=int,
        default=conf['reloc_top'],
        help=f'lln candidates per query for --reloc (default {conf["reloc_top"]})',
    )
    p.add_argument(
        '--reloc-queries', type=int, default=conf['reloc_queries'], help='evenly spaced queries for --reloc (0 = all)'
    )
    p.add_argument('--reloc-detector', default=conf['reloc_detector'], choices=DETECTORS)
    p.add_argument(
        '--reloc-margin',
        type=float,
        default=conf['reloc_margin'],
        help=f'region growth in cells (default {conf["reloc_margin"]:g})',
    )
    p.add_argument(
        '--reloc-fast-threshold',
        type=int,
        default=conf['reloc_fast_threshold'],
        help=f'ORB FAST threshold (default {conf["reloc_fast_threshold"]}; 5 for blurry upsampled '
        'images such as Nordland)',
    )
    p.add_argument(
        '--geometry',
        action='store_true',
        help='instead: metric loop closures on an RGB-D sequence (poses:DIR in the TUM layout with depth/ and '
        'camera_info.yaml) replayed through extractor, localizer and core.geometry; writes results.json `geometry`',
    )
    p.add_argument(
        '--geometry-step', type=int, default=3, help='--geometry: every N-th colour frame (default 3: 10 Hz of 30)'
    )
    p.add_argument(
        '--geometry-swap',
        action='store_true',
        help='--geometry: choose the thresholds on the second half, report on the first (default: the other way)',
    )
    p.add_argument(
        '--geometry-gate',
        nargs=2,
        type=float,
        metavar=('M', 'DEG'),
        help='--geometry: keyframes by an odometry gate (a new one after M metres or DEG degrees), held until '
        '2 s old, queries in localization mode (default: mapping mode, every query a keyframe)',
    )
    p.add_argument(
        '--geometry-novelty',
        type=float,
        metavar='S',
        help='--geometry: mapping mode without odometry, a query stored only when its best S is below S '
        '(keyframe_novelty_max_score), answers at least 2 s older (default: every query a keyframe)',
    )
    p.add_argument('--check', action='store_true', help='read and check every dataset and head, then stop')
    p.add_argument('--quiet', action='store_true', help='no progress output')
    return p


def head_specs(args):
    from ..eval.methods import parse_head

    weights, labels = args.weights or [], args.label or []
    if len(labels) > len(weights):
        raise UsageError(f'--label given {len(labels)} times but --weights only {len(weights)} times')
    try:
        heads = [parse_head(w, labels[i] if i < len(labels) else None) for i, w in enumerate(weights)]
        for group in args.heads or []:
            for item in group.split(','):
                if '=' not in item:
                    raise UsageError(f'--heads items must be LABEL=CKPT (CKPT may be empty), got {item!r}')
                heads.append(parse_head(item))
    except ValueError as e:
        raise UsageError(f'--weights/--heads: {e}') from None
    if len(heads) == 1 and not labels and not args.heads and '=' not in weights[0]:
        heads[0].label = ''  # one unlabelled head: its row is plain `lln`
    if any(h.label and not h.label.replace('_', '').replace('-', '').replace('.', '').isalnum() for h in heads):
        raise UsageError(f'head labels may use letters, digits, _ - . only: {[h.label for h in heads]}')
    return heads


def run(args, argv) -> dict:
    from ..eval import evaluate, load_heads, parse_methods

    log = progress_log(args.quiet)
    try:
        methods = parse_methods(args.methods)
    except ValueError as e:
        raise UsageError(f'--methods: {e}') from None
    if args.top_n < 1 or args.prefilter_k < 0:
        raise UsageError('--top-n must be at least 1 and --prefilter-k at least 0 (0 = every reference)')
    if args.reloc and 'lln' not in methods:
        raise UsageError('--reloc ranks candidates with lln: add lln to --methods')
    if args.reloc and (args.reloc_top < 1 or args.reloc_min_inliers < 1):
        raise UsageError('--reloc-top and --reloc-min-inliers must be at least 1')
    if args.sequence_carry < 0:
        raise UsageError(f'--sequence-carry must be at least 0 (0 = off), got {args.sequence_carry}')
    if args.sequence_acquire_k < 0:
        raise UsageError(f'--sequence-acquire-k must be at least 0 (0 = off), got {args.sequence_acquire_k}')
    if args.sequence_prefilter_k < 0:
        raise UsageError(f'--sequence-prefilter-k must be at least 0 (0 = every ref), got {args.sequence_prefilter_k}')
    if args.sequence < 0:
        raise UsageError(f'--sequence must be 0 (off) or a length of at least 1, got {args.sequence}')
    if args.geometry:
        return run_geometry(args, argv, log)
    from ..io.datasets import parse_range

    frac = parse_range(args.range)
    heads = head_specs(args)

    # 1. read and check every dataset (the readers decode every image) before anything is computed
    loaded = [read_dataset(spec, frac, args.download) for spec in args.dataset]
    if frac and not any(use for _, use in loaded):
        raise UsageError('--range applies to aligned: datasets only, and none was given')

    # 2. the model and every head (checkpoint metadata must fit the backbone)
    from ..core.extractor import Extractor

    extractor = Extractor(extractor_conf(args, num_threads=args.threads))
    heads = load_heads(extractor, heads)

    # 3. downloads last: nothing is fetched when another input is bad
    for i, (spec, (ds, _)) in enumerate(zip(args.dataset, loaded)):
        if ds is None:
            loaded[i] = (download_dataset(PROG, spec, args.download_url, args.quiet, log), None)
    dsets = [ds for ds, _ in loaded]
    for spec, ds in zip(args.dataset, dsets):
        log(f'{PROG}: {ds.name}: {len(ds.query_paths)} queries, {len(ds.ref_paths)} refs ({spec})')
    if args.check:
        return {'checked': [ds.name for ds in dsets]}

    conf = {
        'methods': methods,
        'top_n': args.top_n,
        'prefilter': args.prefilter,
        'prefilter_k': args.prefilter_k,
        'scale': args.scale,
        'similarity_center': args.similarity_center,
        'landmark_whitening': args.landmark_whitening,
        'landmark_knn': args.landmark_knn,
        'landmark_alpha': args.landmark_alpha,
        'similarity_whitening': args.similarity_whitening,
        'similarity_fusion': args.similarity_fusion,
        'sequence': args.sequence,
        'sequence_prefilter_k': args.sequence_prefilter_k,
        'sequence_carry': args.sequence_carry,
        'sequence_acquire_k': args.sequence_acquire_k,
        'sequence_score_norm': args.sequence_score_norm,
        'timing_images': args.timing_images,
        'timing_queries': args.timing_queries,
        'timing_repeats': args.timing_repeats,
        'examples': args.examples,
        'heatmap_images': args.heatmap_images,
        'cache_dir': args.cache,
        'plots': not args.no_plots,
        'progress': not args.quiet,
        'reloc': args.reloc,
        'reloc_min_inliers': args.reloc_min_inliers,
        'reloc_top': args.reloc_top,
        'reloc_queries': args.reloc_queries,
        'reloc_detector': args.reloc_detector,
        'reloc_margin': args.reloc_margin,
        'reloc_fast_threshold': args.reloc_fast_threshold,
    }
    command = f'{PROG} ' + ' '.join(shlex.quote(a) for a in argv)
    result = evaluate(dsets, extractor, conf, heads, args.out, specs=args.dataset, command=command, log=log)
    if not any(h.trained for h in heads) and 'lln' in methods:
        log(f'{PROG}: note: every LLN head evaluated is untrained (Xavier init)')
    return {'out': args.out, 'figures': result.figures}


def run_geometry(args, argv, log) -> dict:
    """lln-eval --geometry: every --dataset poses:DIR read as a TUM RGB-D sequence (io.rgbd), replayed
    (eval.geometry), its `geometry` object written to --out/results.json (one dataset: the object
    itself; several: keyed by name)."""
    from ..core.extractor import Extractor
    from ..eval.geometry import evaluate_geometry, write
    from ..io.rgbd import read_tum

    if args.geometry_step < 1:
        raise UsageError(f'--geometry-step must be at least 1, got {args.geometry_step}')
    roots = []
    for spec in args.dataset:
        kind, _, rest = spec.partition(':')
        if kind != 'poses' or not rest:
            raise UsageError(f'--geometry needs --dataset poses:DIR (a TUM RGB-D folder), got {spec!r}')
        roots.append(rest.split(',')[0])
    seqs = [read_tum(root, {'step': args.geometry_step}) for root in roots]  # every input checked first
    for seq in seqs:
        log(f'{PROG}: {seq.name}: {len(seq)} RGB-D frames ({seq.info["frames_without_depth"]} without depth)')
    if args.check:
        return {'checked': [s.name for s in seqs]}
    extractor = Extractor(extractor_conf(args, num_threads=args.threads))
    conf = {'swap': args.geometry_swap}
    if args.geometry_gate:
        if min(args.geometry_gate) < 0:
            raise UsageError(f'--geometry-gate M DEG must not be negative, got {args.geometry_gate}')
        conf.update(gate=True, gate_m=args.geometry_gate[0], gate_deg=args.geometry_gate[1])
    if args.geometry_novelty is not None:
        if not args.geometry_novelty > 0 or args.geometry_gate:
            raise UsageError(f'--geometry-novelty S needs S > 0 and no --geometry-gate, got {args.geometry_novelty}')
        conf.update(novelty=args.geometry_novelty)
    results = {s.name: evaluate_geometry(s, extractor, conf, progress=not args.quiet) for s in seqs}
    command = f'{PROG} ' + ' '.join(shlex.quote(a) for a in argv)
    obj = next(iter(results.values())) if len(results) == 1 else results
    path = write(args.out, obj, command)
    log(f'{PROG}: geometry written to {path}')
    return {'out': args.out, 'geometry': str(path)}


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.threads > 0:
        # numpy's BLAS (the matching GEMMs) spins its own threads; on a shared CPU two of them contend
        # badly, so --threads caps it too. Only effective before numpy loads (the console script);
        # a variable the user set wins.
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            os.environ.setdefault(var, str(args.threads))

    def go() -> int:
        out = run(args, argv)
        if 'geometry' in out:
            print(f'{PROG}: wrote {out["geometry"]}')
        elif 'checked' in out:
            print(f'{PROG}: {len(out["checked"])} dataset(s) OK: {", ".join(out["checked"])}')
        else:
            out_dir = Path(out['out'])
            print(f'{PROG}: wrote {out_dir / "results.json"}, {out_dir / "results.md"} and {len(out["figures"])} PNGs')
        return 0

    return run_cli(PROG, go)


if __name__ == '__main__':
    sys.exit(main())
