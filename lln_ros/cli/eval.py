"""lln-eval: every place-recognition method on every dataset, with the paper's protocol and pictures.

    lln-eval --dataset SPEC [--dataset SPEC ...] --out DIR [--methods holistic,lln,act,rand,all]
             [--top-n 50] [--prefilter landmarks|holistic|exhaustive] [--prefilter-k 30|0]
             [--range START:END] [--sequence L]
             [--weights [LABEL=]CKPT ...] [--label NAME ...] [--heads LABEL=CKPT,LABEL=,...]
             [--backbone NAME] [--layer LAYER] [--cache DIR] [--download [--download-url URL]]

SPEC: vprbench:DIR | aligned:DIR_REF,DIR_QUERY[,TOL] | loop:DIR,GT_FILE | gardenspoint:DIR[,REF,QUERY].
--range START:END (fractions) selects that part of every `aligned:` dataset (e.g. 0.7:1 = the last 30%
of the route); other kinds are used whole. Each head named by --weights / --heads is its own row
`lln[LABEL]`: `--heads trained=best.pt,untrained=` compares a trained head with the untrained
(seeded Xavier) head in one run. An empty CKPT (or `xavier`) is the untrained head, `shipped` the head
shipped with the package; without any, the row `lln` uses the shipped head (untrained if none ships).
act / rand / all / holistic do not depend on the head and get one row each. The classic peers
`sad` and `seqslam` (SeqSLAM, Milford and Wyeth 2012) are methods too; --sequence L adds an `X+seq`
row per holistic/local row: its scores through the matcher's online sequence search (L queries).

Every dataset is read and checked, and every head loaded, before any feature is computed. Bad input
exits 2 with one line on stderr. Writes DIR/results.json, DIR/results.md and PNGs.
"""
from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

PROG = 'lln-eval'


class UsageError(Exception):
    """Bad command-line values found after argparse (one line, exit 2)."""


def build_parser() -> argparse.ArgumentParser:
    from ..landmark_index import PREFILTERS
    from ..retrieval import default_conf as retrieval_conf
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.strip().splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog='\n'.join(__doc__.strip().splitlines()[1:]))
    p.add_argument('--dataset', action='append', required=True, metavar='SPEC', help='dataset (repeatable)')
    p.add_argument('--methods', default='holistic,lln,act,rand,all',
                   help='comma-separated subset of holistic,lln,act,rand,all,sad,seqslam '
                        '(default: holistic,lln,act,rand,all)')
    p.add_argument('--top-n', type=int, default=50, help='landmarks per image for lln/act/rand (default 50)')
    p.add_argument('--prefilter', default=retrieval_conf['prefilter'], choices=PREFILTERS,
                   help=f"first stage every local method's rerank starts from: landmarks (each query landmark's "
                        f"nearest map landmarks, voted per reference), holistic (global cosine, the paper's) or "
                        f"exhaustive (every reference) (default {retrieval_conf['prefilter']})")
    p.add_argument('--prefilter-k', type=int, default=retrieval_conf['prefilter_k'],
                   help=f"first-stage candidates every local method reranks (default {retrieval_conf['prefilter_k']}; "
                        '0 = every reference, an exhaustive rerank, whatever --prefilter says)')
    p.add_argument('--scale', type=float, default=1.0, help='offset-weight width in grid cells (default 1)')
    p.add_argument('--sequence', type=int, default=0, metavar='L',
                   help='add an X+seq row per holistic/local method: sequence search over L queries '
                        '(0 = off; seqslam uses L, or 10)')
    p.add_argument('--out', required=True, metavar='DIR', help='output folder (results.json, results.md, PNGs)')
    p.add_argument('--range', help='START:END fractions of every aligned dataset (e.g. 0.7:1)')
    p.add_argument('--weights', action='append', metavar='[LABEL=]CKPT',
                   help='LLN head checkpoint, one lln row each (repeatable); empty or "xavier" = untrained')
    p.add_argument('--label', action='append', metavar='NAME',
                   help='row label for the --weights given in the same position (repeatable)')
    p.add_argument('--heads', action='append', metavar='LABEL=CKPT[,LABEL=CKPT]',
                   help='several labelled heads at once, e.g. trained=best.pt,untrained=')
    p.add_argument('--backbone', default='efficientnet_lite0')
    p.add_argument('--layer', default='', help="backbone feature layer (default: the backbone's)")
    p.add_argument('--backbone-weights', default='', help='local backbone state dict (resnet101 needs one)')
    p.add_argument('--input-height', type=int, default=288, help='network input height (default 288)')
    p.add_argument('--cache', default='cache/features', help='backbone feature cache (default cache/features)')
    p.add_argument('--download', action='store_true',
                   help='gardenspoint:DIR lacking its folders: fetch GardensPoint_Walking.zip into DIR')
    p.add_argument('--download-url', default=None, help='where --download fetches from (default: the public archive)')
    p.add_argument('--threads', type=int, default=0,
                   help='torch threads, and numpy BLAS threads when run as a command (0 = defaults)')
    p.add_argument('--timing-images', type=int, default=5, help='images per dataset extraction is timed on')
    p.add_argument('--timing-queries', type=int, default=10, help='queries per dataset matching is timed on')
    p.add_argument('--timing-repeats', type=int, default=3, help='timing rounds; the best of them counts')
    p.add_argument('--examples', type=int, default=2, help='success and failure match pictures per dataset')
    p.add_argument('--heatmap-images', type=int, default=4, help='images in the heatmap figure (0 = none)')
    p.add_argument('--no-plots', action='store_true', help='write results.json and results.md only')
    p.add_argument('--reloc', action='store_true',
                   help='also relocalization: top-5 lln candidates, region-constrained vs all-keypoint matching')
    p.add_argument('--reloc-min-inliers', type=int, default=30, help='inliers a true candidate needs (default 30)')
    p.add_argument('--reloc-top', type=int, default=5, help='lln candidates per query for --reloc (default 5)')
    p.add_argument('--reloc-queries', type=int, default=0, help='evenly spaced queries for --reloc (0 = all)')
    p.add_argument('--reloc-detector', default='orb', choices=['orb', 'sift', 'akaze'])
    p.add_argument('--reloc-margin', type=float, default=1.0, help='region growth in cells (default 1)')
    p.add_argument('--reloc-fast-threshold', type=int, default=20,
                   help='ORB FAST threshold (default 20; 5 for blurry upsampled images such as Nordland)')
    p.add_argument('--check', action='store_true', help='read and check every dataset and head, then stop')
    p.add_argument('--quiet', action='store_true', help='no progress output')
    return p


def head_specs(args):
    from ..evaluation import parse_head
    weights, labels = args.weights or [], args.label or []
    if len(labels) > len(weights):
        raise UsageError(f'--label given {len(labels)} times but --weights only {len(weights)} times')
    heads = [parse_head(w, labels[i] if i < len(labels) else None) for i, w in enumerate(weights)]
    for group in args.heads or []:
        for item in group.split(','):
            if '=' not in item:
                raise UsageError(f'--heads items must be LABEL=CKPT (CKPT may be empty), got {item!r}')
            heads.append(parse_head(item))
    if len(heads) == 1 and not labels and not args.heads and '=' not in weights[0]:
        heads[0].label = ''  # one unlabelled head: its row is plain `lln`
    if any(h.label and not h.label.replace('_', '').replace('-', '').replace('.', '').isalnum() for h in heads):
        raise UsageError(f'head labels may use letters, digits, _ - . only: {[h.label for h in heads]}')
    return heads


def load_dataset(spec: str, frac, download: bool):
    """(Dataset or None when it must be downloaded first, the --range it got)."""
    from .. import datasets
    from ..errors import DatasetError
    from ..evaluation import GARDENS_POINT_FOLDERS
    kind, _, rest = spec.partition(':')
    if kind == 'gardenspoint':
        args = [a for a in rest.split(',') if a]
        if len(args) in (1, 3):
            root = Path(args[0])
            need = args[1:] or ['day_right', 'night_right']
            if not all((root / f).is_dir() for f in need):
                if download:
                    return None, None
                raise DatasetError(f'{root} is not the Gardens Point Walking layout '
                                   f'({", ".join(f + "/" for f in GARDENS_POINT_FOLDERS)}); '
                                   f'add --download to fetch GardensPoint_Walking.zip into it')
    use = frac if kind == 'aligned' else None
    ds = datasets.parse_spec(spec, use)
    if use:
        ds.name = f'{ds.name}[{use[0]:g}:{use[1]:g}]'
    return ds, use


def run(args, argv) -> dict:
    from .. import datasets
    from ..evaluation import GARDENS_POINT_URL, evaluate, fetch_gardenspoint, load_heads, parse_methods

    log = (lambda msg: None) if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
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
    if args.sequence < 0:
        raise UsageError(f'--sequence must be 0 (off) or a length of at least 1, got {args.sequence}')
    from ..datasets import parse_range
    frac = parse_range(args.range)
    heads = head_specs(args)

    # 1. read and check every dataset (the readers decode every image) before anything is computed
    loaded = [load_dataset(spec, frac, args.download) for spec in args.dataset]
    if frac and not any(use for _, use in loaded):
        raise UsageError('--range applies to aligned: datasets only, and none was given')

    # 2. the model and every head (checkpoint metadata must fit the backbone)
    from ..extractor import Extractor
    extractor = Extractor({'backbone': {'name': args.backbone, 'layer': args.layer,
                                        'weights_path': args.backbone_weights},
                           'top_n': args.top_n, 'input_height': args.input_height,
                           'num_threads': args.threads})
    heads = load_heads(extractor, heads)

    # 3. downloads last: nothing is fetched when another input is bad
    for i, (spec, (ds, _)) in enumerate(zip(args.dataset, loaded)):
        if ds is None:
            root = spec.partition(':')[2].split(',')[0]
            url = args.download_url or GARDENS_POINT_URL
            log(f'{PROG}: {root} lacks the Gardens Point folders; downloading {url}')
            fetch_gardenspoint(root, url, progress=not args.quiet)
            loaded[i] = (datasets.parse_spec(spec), None)
    dsets = [ds for ds, _ in loaded]
    for spec, ds in zip(args.dataset, dsets):
        log(f'{PROG}: {ds.name}: {len(ds.query_paths)} queries, {len(ds.ref_paths)} refs ({spec})')
    if args.check:
        return {'checked': [ds.name for ds in dsets]}

    conf = {'methods': methods, 'top_n': args.top_n, 'prefilter': args.prefilter, 'prefilter_k': args.prefilter_k,
            'scale': args.scale,
            'sequence': args.sequence,
            'timing_images': args.timing_images, 'timing_queries': args.timing_queries,
            'timing_repeats': args.timing_repeats,
            'examples': args.examples, 'heatmap_images': args.heatmap_images, 'cache_dir': args.cache,
            'plots': not args.no_plots, 'progress': not args.quiet,
            'reloc': args.reloc, 'reloc_min_inliers': args.reloc_min_inliers, 'reloc_top': args.reloc_top,
            'reloc_queries': args.reloc_queries, 'reloc_detector': args.reloc_detector,
            'reloc_margin': args.reloc_margin, 'reloc_fast_threshold': args.reloc_fast_threshold}
    command = f'{PROG} ' + ' '.join(shlex.quote(a) for a in argv)
    result = evaluate(dsets, extractor, conf, heads, args.out, specs=args.dataset, command=command, log=log)
    if not any(h.trained for h in heads) and 'lln' in methods:
        log(f'{PROG}: note: every LLN head evaluated is untrained (Xavier init)')
    return {'out': args.out, 'figures': result.figures}


def main(argv=None) -> int:
    from ..errors import LLNError
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if args.threads > 0:
        # numpy's BLAS (the matching GEMMs) spins its own threads; on a shared CPU two of them contend
        # badly, so --threads caps it too. Only effective before numpy loads (the console script);
        # a variable the user set wins.
        for var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
            os.environ.setdefault(var, str(args.threads))
    try:
        out = run(args, argv)
    except (LLNError, UsageError) as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f'{PROG}: interrupted', file=sys.stderr)
        return 130
    if 'checked' in out:
        print(f'{PROG}: {len(out["checked"])} dataset(s) OK: {", ".join(out["checked"])}')
    else:
        out_dir = Path(out['out'])
        print(f'{PROG}: wrote {out_dir / "results.json"}, {out_dir / "results.md"} and '
              f'{len(out["figures"])} PNGs')
    return 0


if __name__ == '__main__':
    sys.exit(main())
