"""lln-export: export the extractor's network (backbone to the layer + LLN head) to ONNX.

    lln-export [--backbone efficientnet_lite0] [--layer stage6] [--weights HEAD.pt] [--output FILE.onnx]

Never needed by hand: the extractor exports on first use into the cache (lln_ros.core.runtime; default
~/.cache/lln_ros/onnx, or $LLN_CACHE/onnx) and reuses the file. This command fills that cache ahead
of time, or writes a file elsewhere with --output, and checks the exported graph against torch on a
real photograph (the largest feature and logit difference is printed).
"""

from __future__ import annotations

import argparse
import json
import sys

from ..errors import LLNError

PROG = 'lln-export'


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.strip().splitlines()[0])
    p.add_argument('--backbone', default='efficientnet_lite0')
    p.add_argument('--layer', default='', help="backbone feature layer (default: the backbone's)")
    p.add_argument('--backbone-weights', default='', help='local backbone state dict (resnet101 needs one)')
    p.add_argument('--weights', default='', help='LLN head checkpoint (default: the shipped one)')
    p.add_argument('--output', default='', help='write the graph here instead of the cache')
    p.add_argument('--force', action='store_true', help='export again even when the cached file exists')
    p.add_argument('--json', action='store_true', help='print one JSON object')
    return p


def run(args) -> dict:
    import numpy as np

    from ..core import runtime
    from ..core.extractor import Extractor
    from ..io.image import resize_for_network

    # the torch extractor builds and checks the model exactly as extraction does
    ex = Extractor(
        {
            'backbone': {'name': args.backbone, 'layer': args.layer, 'weights_path': args.backbone_weights},
            'weights': args.weights,
            'runtime': 'torch',
        }
    )
    name, layer = ex.model_info['backbone'], ex.model_info['layer']
    path = runtime.onnx_path(name, layer, ex.backbone, ex.head)
    if args.output:
        path = runtime.export_onnx(ex.backbone, ex.head, args.output)
    elif args.force or not path.is_file():
        path = runtime.export_onnx(ex.backbone, ex.head, path)
    if not runtime.onnxruntime_available():
        raise LLNError(f'exported {path}, but onnxruntime is not installed to check it (pip install onnxruntime)')
    import matplotlib.cbook as cbook

    from ..io.image import load_image

    with cbook.get_sample_data('grace_hopper.jpg') as f:
        rgb = resize_for_network(load_image(f.name), 288)[None]
    t_feats, t_logits = ex.network(rgb)
    o_feats, o_logits = runtime.OnnxRuntimeNetwork(path)(rgb)
    return {
        'path': str(path),
        'model': {**ex.model_info, 'runtime': 'onnxruntime'},
        'check_input': list(rgb.shape[1:3][::-1]),
        'max_feature_diff': float(np.abs(t_feats - o_feats).max()),
        'max_logit_diff': float(np.abs(t_logits - o_logits).max()),
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        out = run(args)
    except LLNError as e:
        print(f'{PROG}: error: {e}', file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(out))
    else:
        print(f'{out["path"]}')
        print(
            f'checked against torch at {out["check_input"][0]}x{out["check_input"][1]}: largest difference '
            f'{out["max_feature_diff"]:.2g} in features, {out["max_logit_diff"]:.2g} in logits'
        )
    return 0


if __name__ == '__main__':
    sys.exit(main())
