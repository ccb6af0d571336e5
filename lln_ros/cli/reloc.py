"""lln-reloc: place matching plus keypoint relocalization of one query against one keyframe.

    lln-reloc QUERY KEYFRAME [--detector orb|sift|akaze] [--intrinsics camera.yaml]
              [--plot out.png] [--json]

Runs LLN place matching (the mutually matched landmark regions), then keypoint matching twice:
only inside the matched region pairs (mLLN) and all keypoints against all (the plain baseline),
each followed by RANSAC (fundamental matrix; essential matrix and relative pose with --intrinsics).
"""

from __future__ import annotations

import argparse
import json
import sys

from .common import add_model_arguments, check_output_file, run_cli
from .match import extractor_from_args

PROG = 'lln-reloc'


def build_parser() -> argparse.ArgumentParser:
    from ..core.reloc import DETECTORS, default_conf

    p = argparse.ArgumentParser(prog=PROG, description=__doc__.strip().splitlines()[0])
    p.add_argument('query')
    p.add_argument('keyframe')
    p.add_argument('--detector', default=default_conf['detector'], choices=DETECTORS)
    p.add_argument('--max-keypoints', type=int, default=default_conf['max_keypoints'])
    p.add_argument('--ratio', type=float, default=default_conf['ratio'], help='Lowe ratio (default 0.8)')
    p.add_argument(
        '--margin',
        type=float,
        default=default_conf['margin'],
        help='region growth in grid cells on each side (default 1)',
    )
    p.add_argument(
        '--min-inliers',
        type=int,
        default=default_conf['min_inliers'],
        help='RANSAC inliers needed to call a pair verified (default 15)',
    )
    p.add_argument(
        '--intrinsics',
        metavar='YAML',
        help='ROS camera-calibration YAML (camera_matrix) or a YAML with K: essential matrix + pose',
    )
    add_model_arguments(p)
    p.add_argument('--plot', metavar='PNG', help="write both pipelines' inlier matches side by side")
    p.add_argument('--json', action='store_true', help='print one JSON object instead of text')
    return p


def run(args) -> dict:
    from ..core.reloc import Relocalizer, camera_matrix, pair_boxes
    from ..core.similarity import match_pair
    from ..io.image import load_image

    check_output_file(args.plot, '--plot')
    images = [load_image(args.query), load_image(args.keyframe)]
    K = camera_matrix(args.intrinsics) if args.intrinsics else None
    reloc = Relocalizer(
        {
            'detector': args.detector,
            'max_keypoints': args.max_keypoints,
            'ratio': args.ratio,
            'margin': args.margin,
            'min_inliers': args.min_inliers,
        }
    )
    extractor = extractor_from_args(args)
    a, b = extractor.extract_batch(images)
    place = match_pair(a, b)
    pairs = place.pairs(0)
    qb, mb = pair_boxes(a, b, pairs, args.margin)
    kq, km = reloc.detect(images[0]), reloc.detect(images[1])
    regions = reloc.relocalize(kq, km, qb, mb, K=K)
    plain = reloc.relocalize(kq, km, K=K)
    if args.plot:
        from ..viz.plotting import plot_keypoint_matches

        plot_keypoint_matches(
            images[0],
            images[1],
            [
                {
                    'label': f'mLLN ({len(qb)} region pairs)',
                    'query': kq,
                    'map': km,
                    'result': regions,
                    'query_boxes': qb,
                    'map_boxes': mb,
                },
                {'label': 'all keypoints', 'query': kq, 'map': km, 'result': plain},
            ],
            args.plot,
            title=f'{args.detector}: S = {place.scores[0]:.2f}, {len(qb)} mutual landmark pairs',
        )
    return {
        'inliers_regions': regions.inliers,
        'inliers_all': plain.inliers,
        'ms_regions': regions.matches.ms + regions.ms,
        'ms_all': plain.matches.ms + plain.ms,
        'verified_regions': regions.verified,
        'verified_all': plain.verified,
        'regions': regions.summary(),
        'all': plain.summary(),
        'keypoints': [len(kq), len(km)],
        'detector': args.detector,
        'similarity': float(place.scores[0]),
        'region_pairs': int(len(qb)),
        'model': extractor.model_info,
        'plot': args.plot or None,
    }


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli(PROG, lambda: report(run(args), args.json))


def report(out: dict, as_json: bool) -> int:
    if as_json:
        print(json.dumps(out))
        return 0
    print(
        f'place: S = {out["similarity"]:.3f}, {out["region_pairs"]} mutual landmark pairs; '
        f'{out["keypoints"][0]} / {out["keypoints"][1]} {out["detector"]} keypoints'
    )
    for label, key in (('regions (mLLN)', 'regions'), ('all keypoints', 'all')):
        r = out[key]
        status = 'verified' if r['verified'] else f'not verified ({r["reason"]})'
        print(
            f'{label:<15} {r["inliers"]:4d} inliers / {r["matches"]:4d} matches  {out["ms_" + key]:7.1f} ms  {status}'
        )
    if out['plot']:
        print(f'plot written to {out["plot"]}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
