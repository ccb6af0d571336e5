"""lln-train: train the LLN head on cached backbone features.

    lln-train --data SPEC [--data SPEC ...] [--range START:END] [--val SPEC ...] [--val-range START:END]
              --out DIR [--objective rerank|triplet] [--epochs 10] [--lr 1e-3] [--norm-prior 0] [--seed 0]

--objective rerank (default) trains on a differentiable form of the test-time reranking score;
triplet is the paper's loss on the LLN-weighted embedding (the paper's recipe:
--objective triplet --train-size 352x352 --lr 1e-4). See lln_ros/core/training.py.

SPEC: any lln-eval dataset (aligned:REF,QUERY[,TOL], vprbench:DIR, loop:DIR,GT, gardenspoint:DIR,
poses:DIR[,MAX_DEG,MAX_M,MIN_GAP_S]), or places:DIR (DIR/<place>/*.jpg), or sfm:PICKLE,IMS_ROOT
(Retrieval-SfM-120k layout), or sequence:DIR[,POS_GAP,NEG_GAP]: one traverse of the user's own, no
ground truth (pseudo-labels from frame order: lln_ros/core/adaptation.py; --range applies).
--init shipped fine-tunes the shipped head, --init CKPT another head, each with the head
configuration in its checkpoint (the head flags --norm-prior, --correction-bound and --padding are
for a head trained from scratch); the default starts from scratch. Datasets of different image
shapes mix. --val is repeatable: the head with the best MEAN validation precision at 100% recall
over all --val sets is DIR/best.pt; DIR/last.pt resumes an interrupted run.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys

from .common import UsageError, run_cli


def build_parser() -> argparse.ArgumentParser:
    # the defaults live with the head and the trainer (core stays a lazy import of the cli)
    from ..core.lln import PADDINGS
    from ..core.lln import default_conf as lln_defaults
    from ..core.training import default_conf as train_defaults

    p = argparse.ArgumentParser(prog='lln-train', description=__doc__.strip().splitlines()[0])
    p.add_argument('--data', action='append', required=True, metavar='SPEC', help='training data (repeatable)')
    p.add_argument('--range', help='START:END fractions of every aligned --data to train on')
    p.add_argument(
        '--val',
        action='append',
        metavar='SPEC',
        help='validation dataset (an lln-eval SPEC; repeatable: best.pt is best on the mean)',
    )
    p.add_argument('--val-range', help='START:END fractions of every aligned --val')
    p.add_argument('--out', required=True, help='output folder (best.pt, last.pt, history.json)')
    p.add_argument(
        '--objective',
        choices=('rerank', 'triplet'),
        default='rerank',
        help="rerank: the test-time score (default) | triplet: the paper's embedding loss",
    )
    p.add_argument('--epochs', type=int, default=10)
    p.add_argument('--lr', type=float, default=1e-3)
    p.add_argument('--batch-size', type=int, default=10, help='tuples per step (paper: 10)')
    p.add_argument('--negatives', type=int, default=4, help='hard negatives per tuple (paper: 4)')
    p.add_argument('--margin', type=float, default=0.3, help='triplet margin')
    p.add_argument('--tau', type=float, default=0.05, help='rerank: softmax temperature on the score')
    p.add_argument('--soft-temp', type=float, default=1.0, help='rerank: width of the soft top-n, in logits')
    p.add_argument('--top-n', type=int, default=50, help='landmarks per image (validation, and rerank training)')
    p.add_argument('--tuples-per-epoch', type=int, default=1000, help='0 = every usable query')
    p.add_argument(
        '--balance-sets',
        action='store_true',
        help='draw the same number of training queries from every --data set per epoch (a small set again)',
    )
    p.add_argument(
        '--train-size',
        default='288',
        help='training input height H (aspect kept, as at test time; default 288), or WxH '
        "to squash (the paper's 352x352)",
    )
    p.add_argument('--neg-margin', type=int, default=10, help='route data: frames beside a match are not negatives')
    p.add_argument(
        '--norm-prior',
        type=float,
        default=lln_defaults['norm_prior'],
        help="weight of log feature norm (ACT's score) in the head's logits; > 0 starts the head "
        "at ACT's selection (default 0: the plain LLN head)",
    )
    p.add_argument(
        '--correction-bound',
        type=float,
        default=lln_defaults['correction_bound'],
        help='with --norm-prior: bound b of the learned correction to log feature norm (b tanh(c / b)); 0 = unbounded',
    )
    p.add_argument(
        '--padding',
        choices=PADDINGS,
        default=lln_defaults['padding'],
        help="how the head's 3x3 / 5x5 convs pad the feature map",
    )
    p.add_argument(
        '--crop-views',
        type=int,
        default=train_defaults['crop_views'],
        help='lateral crops of every training query that train as queries too (0 = none)',
    )
    p.add_argument(
        '--crop-range',
        default=':'.join(str(v) for v in train_defaults['crop_range']),
        metavar='LO:HI',
        help='width of a lateral crop as a fraction of the image width',
    )
    p.add_argument(
        '--init',
        default='',
        metavar='shipped|CKPT',
        help="start from this head (fine-tune): 'shipped' = the package's head; default: from scratch",
    )
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--backbone', default='efficientnet_lite0')
    p.add_argument('--layer', default='')
    p.add_argument('--backbone-weights', default='')
    p.add_argument('--cache', default='cache/features', help='feature cache folder')
    p.add_argument('--threads', type=int, default=0, help='torch threads (0 = default)')
    p.add_argument('--no-resume', action='store_true', help='ignore OUT/last.pt')
    return p


def load_pairs(spec: str, frac, neg_margin: int):
    from ..core import training_pairs

    kind, _, rest = spec.partition(':')
    if kind == 'sequence':
        from ..core import adaptation

        return adaptation.parse_sequence_spec(rest, frac)
    if kind == 'places':
        return training_pairs.pairs_from_places(rest)
    if kind == 'sfm':
        pickle_path, _, ims = rest.partition(',')
        return training_pairs.pairs_from_sfm(pickle_path, ims)
    return training_pairs.pairs_from_dataset(load_dataset(spec, frac), neg_margin)


def load_dataset(spec: str, frac):
    """A Dataset; frac (--range / --val-range) applies to aligned specs only and is kept in its name,
    so the checkpoint metadata says which part of a route was trained or validated on."""
    from ..io import datasets

    use = frac if spec.startswith('aligned:') else None
    ds = datasets.parse_spec(spec, use)
    if use:
        ds.name = f'{ds.name}[{use[0]:g}:{use[1]:g}]'
    return ds


def run(args) -> dict:
    from ..core import training, training_pairs
    from ..core.extractor import Extractor
    from ..errors import DatasetError
    from ..io import datasets

    size = args.train_size.lower()
    train_size = tuple(int(v) for v in size.split('x')) if 'x' in size else int(size)
    conf = {
        'objective': args.objective,
        'tau': args.tau,
        'soft_temp': args.soft_temp,
        'val_top_n': args.top_n,
        'epochs': args.epochs,
        'lr': args.lr,
        'batch_size': args.batch_size,
        'negatives': args.negatives,
        'margin': args.margin,
        'tuples_per_epoch': args.tuples_per_epoch,
        'balance_sets': args.balance_sets,
        'train_size': train_size,
        'neg_margin': args.neg_margin,
        'seed': args.seed,
    }
    try:
        conf['crop_range'] = tuple(float(v) for v in args.crop_range.split(':'))
    except ValueError:
        raise DatasetError(f'--crop-range takes LO:HI fractions, got {args.crop_range!r}') from None
    conf['crop_views'] = args.crop_views
    if args.correction_bound and not args.norm_prior:
        raise UsageError('--correction-bound bounds the correction to the norm prior: it needs --norm-prior')
    conf['head'] = {'padding': args.padding}
    if args.norm_prior:
        conf['head'].update(norm_prior=args.norm_prior, correction_bound=args.correction_bound)
    # every dataset is read and checked before any feature is computed
    frac, val_frac = datasets.parse_range(args.range), datasets.parse_range(args.val_range)
    pairs = training_pairs.combine([load_pairs(s, frac, args.neg_margin) for s in args.data])
    val = [load_dataset(v, val_frac) for v in args.val or []]
    extractor = Extractor(
        {
            'backbone': {'name': args.backbone, 'layer': args.layer, 'weights_path': args.backbone_weights},
            'num_threads': args.threads,
        }
    )
    init = None
    if args.init:
        from ..core.extractor import shipped_weights
        from ..core.lln import load_checkpoint

        init = shipped_weights(args.backbone, extractor.backbone.layer) if args.init == 'shipped' else args.init
        if init is None:
            raise DatasetError(f'--init shipped: no head is shipped for {args.backbone}/{extractor.backbone.layer}')
        # fine-tuning keeps the checkpoint's architecture (norm prior, bound, padding): the head
        # flags describe a head trained from scratch
        head_conf = load_checkpoint(init)[0].conf
        conf['head'] = {k: v for k, v in head_conf.items() if k != 'seed'}
    command = 'lln-train ' + ' '.join(shlex.quote(a) for a in sys.argv[1:])
    trainer = training.Trainer(
        extractor, pairs, val, conf, cache_dir=args.cache, out_dir=args.out, meta={'command': command}
    )
    if init:
        from ..core import adaptation

        adaptation.start_from(trainer, init)
    return trainer.fit(resume=not args.no_resume)


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    def go() -> int:
        result = run(args)
        print(json.dumps({'best_val_p_at_100r': result['best_val_p_at_100r']}))
        return 0

    return run_cli(
        'lln-train', go, interrupted='interrupted; OUT/last.pt holds the last finished epoch (rerun to resume)'
    )


if __name__ == '__main__':
    sys.exit(main())
