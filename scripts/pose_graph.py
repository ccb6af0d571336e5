#!/usr/bin/env python3
"""A pose graph in plain numpy that takes the matcher's loop closures as they come (docs/slam_integration.md).

    python scripts/pose_graph.py --odometry poses.txt --closures closures.jsonl [--out optimised.txt]
    python scripts/pose_graph.py --demo       # a drifting square loop closed by one loop closure

poses.txt: `stamp_s tx ty tz qx qy qz qw` per line (the camera's odometry poses, TUM layout);
closures.jsonl: scripts/loop_closure_client.py's lines with an accepted pose (--require-pose):
`transform` is T(keyframe <- query), `covariance` its 6x6 of [x y z roll pitch yaw]. Each closure
becomes an edge between the odometry poses nearest its two stamps, weighted by the inverse of its
covariance; consecutive odometry poses are edges weighted by --odom-sigma. Gauss-Newton on the
perturbation the matcher's covariance is defined in (lln_ros.core.geometry: t + d_t, exp([d_r]x) R),
the first pose held fixed. Dense normal equations: fine for a few hundred poses; use GTSAM or g2o
beyond that, with the same edges.
"""

from __future__ import annotations

import argparse
import json
import sys

import cv2
import numpy as np


def perturb(T, d):
    out = T.copy()
    out[:3, :3] = cv2.Rodrigues(np.asarray(d[3:], np.float64).reshape(3, 1))[0] @ T[:3, :3]
    out[:3, 3] = T[:3, 3] + d[:3]
    return out


def inv(T):
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = T[:3, :3].T, -T[:3, :3].T @ T[:3, 3]
    return out


def residual(Ti, Tj, Z):
    """d (6,) with perturb(Z, d) = Ti^-1 Tj: the edge's error in the convention of its covariance."""
    P = inv(Ti) @ Tj
    return np.r_[P[:3, 3] - Z[:3, 3], cv2.Rodrigues(P[:3, :3] @ Z[:3, :3].T)[0].ravel()]


def optimise(poses: list, edges: list, iterations: int = 20, eps: float = 1e-6) -> list:
    """poses: [T (4, 4)]; edges: [(i, j, Z (4, 4) measured Ti^-1 Tj, information (6, 6))]."""
    X = [np.array(T, np.float64) for T in poses]
    n = len(X)
    for _ in range(iterations):
        H, b = np.zeros((6 * n, 6 * n)), np.zeros(6 * n)
        for i, j, Z, info in edges:
            r = residual(X[i], X[j], Z)
            J = np.zeros((6, 12))
            for k in range(6):  # numerical Jacobians w.r.t. each pose's own perturbation
                d = np.zeros(6)
                d[k] = eps
                J[:, k] = (residual(perturb(X[i], d), X[j], Z) - residual(perturb(X[i], -d), X[j], Z)) / (2 * eps)
                J[:, 6 + k] = (residual(X[i], perturb(X[j], d), Z) - residual(X[i], perturb(X[j], -d), Z)) / (2 * eps)
            idx = np.r_[6 * i : 6 * i + 6, 6 * j : 6 * j + 6]
            H[np.ix_(idx, idx)] += J.T @ info @ J
            b[idx] += J.T @ info @ r
        H[:6, :6] += 1e12 * np.eye(6)  # the first pose is the origin of the map: held
        dx = np.linalg.solve(H + 1e-9 * np.eye(6 * n), -b)
        X = [perturb(T, dx[6 * k : 6 * k + 6]) for k, T in enumerate(X)]
        if np.abs(dx).max() < 1e-9:
            break
    return X


def odometry_edges(poses, sigma_m: float, sigma_rad: float) -> list:
    info = np.diag([1 / sigma_m**2] * 3 + [1 / sigma_rad**2] * 3)
    return [(k, k + 1, inv(poses[k]) @ poses[k + 1], info) for k in range(len(poses) - 1)]


def closure_edges(stamps: np.ndarray, closures: list) -> list:
    edges = []
    for c in closures:
        if c.get('transform') is None:
            continue
        i = int(np.argmin(np.abs(stamps - c['keyframe_stamp_ns'] * 1e-9)))
        j = int(np.argmin(np.abs(stamps - c['query_stamp_ns'] * 1e-9)))
        cov = np.asarray(c['covariance'], np.float64).reshape(6, 6)
        edges.append((i, j, np.asarray(c['transform'], np.float64), np.linalg.inv(cov)))
    return edges


def demo() -> int:
    """A square of 40 poses (1 m sides) with odometry that drifts 1 deg per step in yaw, closed by one
    loop closure (last pose <- first pose, the truth plus 1 cm / 0.5 deg noise)."""
    rng = np.random.default_rng(0)
    truth = []
    for k in range(40):
        side, f = divmod(k, 10)
        yaw = side * np.pi / 2
        corner = [(0, 0), (1, 0), (1, 1), (0, 1)][side]
        T = np.eye(4)
        T[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.0, yaw]))[0]
        T[:3, 3] = [corner[0] + 0.1 * f * np.cos(yaw), corner[1] + 0.1 * f * np.sin(yaw), 0]
        truth.append(T)
    odom = [truth[0]]
    for k in range(39):
        step = perturb(inv(truth[k]) @ truth[k + 1], np.r_[0, 0, 0, 0, 0, np.radians(1.0)])
        odom.append(odom[-1] @ step)
    Z = perturb(inv(truth[0]) @ truth[39], np.r_[rng.normal(0, 0.01, 3), rng.normal(0, np.radians(0.5), 3)])
    cov = np.diag([0.01**2] * 3 + [np.radians(0.5) ** 2] * 3)
    edges = odometry_edges(odom, 0.02, np.radians(2.0)) + [(0, 39, Z, np.linalg.inv(cov))]
    out = optimise(odom, edges)
    err = lambda X: max(np.linalg.norm(a[:3, 3] - t[:3, 3]) for a, t in zip(X, truth))  # noqa: E731
    print(f'largest position error: odometry {err(odom):.3f} m, after the loop closure {err(out):.3f} m')
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--demo', action='store_true', help='a synthetic drifting loop, closed')
    p.add_argument('--odometry', help='poses file: stamp_s tx ty tz qx qy qz qw per line')
    p.add_argument('--closures', help="loop_closure_client.py's JSON lines")
    p.add_argument('--odom-sigma', type=float, nargs=2, default=(0.02, 0.02), metavar=('M', 'RAD'))
    p.add_argument('--out', help='write the optimised poses here (same layout); default stdout')
    args = p.parse_args(argv)
    if args.demo:
        return demo()
    if not (args.odometry and args.closures):
        p.error('give --odometry and --closures, or --demo')
    rows = np.loadtxt(args.odometry, comments='#', ndmin=2)
    from lln_ros.core.registration import pose_from_parts, pose_vector

    poses = [pose_from_parts(r[1:4], r[4:8] / np.linalg.norm(r[4:8])) for r in rows]
    with open(args.closures) as f:
        closures = [json.loads(line) for line in f if line.strip()]
    loops = closure_edges(rows[:, 0], closures)
    out = optimise(poses, odometry_edges(poses, *args.odom_sigma) + loops)
    text = '\n'.join(' '.join(f'{v:.6f}' for v in (t, *pose_vector(T))) for t, T in zip(rows[:, 0], out))
    (open(args.out, 'w') if args.out else sys.stdout).write(text + '\n')
    print(f'pose_graph: {len(poses)} poses, {len(loops)} loop closures', file=sys.stderr)
    return 0


if __name__ == '__main__':
    sys.exit(main())
