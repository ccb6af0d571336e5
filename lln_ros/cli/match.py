"""lln-match: how similar are two images, and which regions match?

    lln-match A.jpg B.jpg [--method lln|act|rand|all] [--top-n 50] [--runtime onnxruntime|torch]
              [--plot out.png] [--json]
"""
from __future__ import annotations

import argparse
import json
import sys

from ..errors import LLNError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='lln-match', description=__doc__.strip().splitlines()[0])
    p.add_argument('image_a')
    p.add_argument('image_b')
    p.add_argument('--method', default='lln', choices=['lln', 'act', 'rand', 'all'])
    add_model_arguments(p)
    p.add_argument('--scale', type=float, default=1.0, help='offset-weight width in grid cells (default 1)')
    p.add_argument('--plot', metavar='PNG', help='write the two images with matched regions linked')
    p.add_argument('--json', action='store_true', help='print one JSON object instead of text')
    return p


def add_model_arguments(p: argparse.ArgumentParser) -> None:
    """The extractor options every pair command shares (lln-match, lln-reloc)."""
    p.add_argument('--top-n', type=int, default=50, help='landmarks per image (default 50)')
    p.add_argument('--input-height', type=int, default=288, help='network input height (default 288)')
    p.add_argument('--backbone', default='efficientnet_lite0')
    p.add_argument('--layer', default='', help='backbone feature layer (default: the backbone\'s)')
    p.add_argument('--backbone-weights', default='', help='local backbone state dict (resnet101 needs one)')
    p.add_argument('--weights', default='', help='LLN head checkpoint (default: the shipped one)')
    add_runtime_argument(p)


def add_runtime_argument(p: argparse.ArgumentParser) -> None:
    """--runtime, for every command that builds an Extractor (the default lives in its default_conf)."""
    p.add_argument('--runtime', default=None,
                   help='what runs the network: onnxruntime | torch (default onnxruntime, torch when '
                        'ONNX Runtime is not installed); the landmarks are the same')


def runtime_conf(args) -> dict:
    """{'runtime': ...} when --runtime was given, else {} (the extractor's default applies)."""
    return {'runtime': args.runtime} if getattr(args, 'runtime', None) else {}


def extractor_from_args(args, method: str = 'lln'):
    from ..extractor import Extractor
    return Extractor({
        'backbone': {'name': args.backbone, 'layer': args.layer, 'weights_path': args.backbone_weights},
        'weights': args.weights, 'top_n': args.top_n, 'method': method, 'input_height': args.input_height,
        **runtime_conf(args)})


def run(args) -> dict:
    from ..image import load_image
    from ..similarity import match_pair

    images = [load_image(args.image_a), load_image(args.image_b)]
    extractor = extractor_from_args(args, args.method)
    a, b = extractor.extract_batch(images)
    result = match_pair(a, b, args.scale)
    pairs = result.pairs(0)
    if args.plot:
        from ..plotting import plot_matches
        plot_matches(images[0], images[1], a, b, pairs, args.plot,
                     title=f'{args.method}: S = {result.scores[0]:.2f}, {len(pairs["weight"])} mutual pairs, '
                           f'offset {tuple(int(v) for v in result.offsets[0])} cells')
    return {
        'similarity': float(result.scores[0]),
        'holistic': float(a.global_descriptor @ b.global_descriptor),
        'pairs': int(len(pairs['weight'])),
        'offset': [int(v) for v in result.offsets[0]],
        'n': len(a),
        'method': args.method,
        'grid': [list(a.grid), list(b.grid)],
        'model': extractor.model_info,
        'matches': [{'query_uv': [float(x) for x in a.centers[i]], 'map_uv': [float(x) for x in b.centers[j]],
                     'similarity': float(s), 'weight': float(w)}
                    for i, j, s, w in zip(pairs['query_index'], pairs['map_index'],
                                          pairs['similarity'], pairs['weight'])],
        'plot': args.plot or None,
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        out = run(args)
    except LLNError as e:
        print(f'lln-match: error: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out))
    else:
        print(f'similarity S = {out["similarity"]:.3f}  (holistic cosine {out["holistic"]:.3f})')
        print(f'{out["pairs"]} mutual pairs of {out["n"]} landmarks ({out["method"]}), '
              f'offset (dx, dy) = {tuple(out["offset"])} grid cells')
        if not out['model']['head_trained']:
            print('note: the LLN head is untrained (seeded Xavier init); see README', file=sys.stderr)
        if out['plot']:
            print(f'plot written to {out["plot"]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
