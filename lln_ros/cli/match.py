"""lln-match: how similar are two images, and which regions match?

lln-match A.jpg B.jpg [--method lln|act|rand|all] [--top-n 50] [--runtime onnxruntime|torch]
          [--plot out.png] [--json]
"""

from __future__ import annotations

import argparse
import json
import sys

from .common import add_model_arguments, add_scale_argument, check_output_file, extractor_conf, run_cli

PROG = 'lln-match'


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.strip().splitlines()[0])
    p.add_argument('image_a')
    p.add_argument('image_b')
    from ..core.landmarks import METHODS

    p.add_argument('--method', default=METHODS[0], choices=METHODS)
    add_model_arguments(p)
    add_scale_argument(p)
    p.add_argument('--plot', metavar='PNG', help='write the two images with matched regions linked')
    p.add_argument('--json', action='store_true', help='print one JSON object instead of text')
    return p


def extractor_from_args(args, method: str = 'lln'):
    from ..core.extractor import Extractor

    return Extractor(extractor_conf(args, method=method))


def run(args) -> dict:
    from ..core.similarity import match_pair
    from ..io.image import load_image

    check_output_file(args.plot, '--plot')
    images = [load_image(args.image_a), load_image(args.image_b)]
    extractor = extractor_from_args(args, args.method)
    a, b = extractor.extract_batch(images)
    result = match_pair(a, b, args.scale)
    pairs = result.pairs(0)
    if args.plot:
        from ..viz.plotting import plot_matches

        plot_matches(
            images[0],
            images[1],
            a,
            b,
            pairs,
            args.plot,
            title=f'{args.method}: S = {result.scores[0]:.2f}, {len(pairs["weight"])} mutual pairs, '
            f'offset {tuple(int(v) for v in result.offsets[0])} cells',
        )
    return {
        'similarity': float(result.scores[0]),
        'holistic': float(a.global_descriptor @ b.global_descriptor),
        'pairs': int(len(pairs['weight'])),
        'offset': [int(v) for v in result.offsets[0]],
        'n': len(a),
        'method': args.method,
        'grid': [list(a.grid), list(b.grid)],
        'model': extractor.model_info,
        'matches': [
            {
                'query_uv': [float(x) for x in a.centers[i]],
                'map_uv': [float(x) for x in b.centers[j]],
                'similarity': float(s),
                'weight': float(w),
            }
            for i, j, s, w in zip(pairs['query_index'], pairs['map_index'], pairs['similarity'], pairs['weight'])
        ],
        'plot': args.plot or None,
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)

    def go() -> int:
        out = run(args)
        if args.json:
            print(json.dumps(out))
            return 0
        print(f'similarity S = {out["similarity"]:.3f}  (holistic cosine {out["holistic"]:.3f})')
        print(
            f'{out["pairs"]} mutual pairs of {out["n"]} landmarks ({out["method"]}), '
            f'offset (dx, dy) = {tuple(out["offset"])} grid cells'
        )
        if not out['model']['head_trained']:
            print('note: the LLN head is untrained (seeded Xavier init); see docs/training.md', file=sys.stderr)
        if out['plot']:
            print(f'plot written to {out["plot"]}')
        return 0

    return run_cli(PROG, go)


if __name__ == '__main__':
    sys.exit(main())
