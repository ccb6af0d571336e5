"""Pictures of landmark matches: two images side by side, activation heatmaps, linked regions."""

from __future__ import annotations

import matplotlib

matplotlib.use('Agg')  # files only; nodes and CI have no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import ConnectionPatch, Rectangle  # noqa: E402

from .core.landmarks import LandmarkSet  # noqa: E402
from .io.image import heatmap  # noqa: E402


def plot_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    a: LandmarkSet,
    b: LandmarkSet,
    pairs: dict,
    path: str,
    title: str = '',
    max_links: int = 60,
) -> None:
    """Write a PNG: RGB images side by side with activation overlays, every landmark outlined,
    mutual pairs linked, line opacity = offset weight."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), dpi=110)
    for ax, img, s in ((axes[0], image_a, a), (axes[1], image_b, b)):
        ax.imshow(img)
        if s.activation is not None:
            heat = heatmap(s.activation, (img.shape[1], img.shape[0]))
            ax.imshow(heat, cmap='jet', alpha=0.5 * heat)  # transparent where the head is silent
        for u, v in s.centers:
            w, h = s.cell_size
            ax.add_patch(Rectangle((u - w / 2, v - h / 2), w, h, fill=False, lw=0.5, ec='white', alpha=0.5))
        ax.set_axis_off()
    order = np.argsort(-pairs['weight'] * pairs['similarity'])[:max_links]
    cmap = plt.get_cmap('viridis')
    for j in order:
        qa, mb = pairs['query_index'][j], pairs['map_index'][j]
        wgt = float(pairs['weight'][j])
        colour = cmap(float(pairs['similarity'][j]))
        for ax, s, i in ((axes[0], a, qa), (axes[1], b, mb)):
            w, h = s.cell_size
            u, v = s.centers[i]
            ax.add_patch(Rectangle((u - w / 2, v - h / 2), w, h, fill=False, lw=1.5, ec=colour))
        fig.add_artist(
            ConnectionPatch(
                xyA=tuple(a.centers[qa]),
                coordsA=axes[0].transData,
                xyB=tuple(b.centers[mb]),
                coordsB=axes[1].transData,
                color=colour,
                lw=1.0,
                alpha=max(0.15, wgt),
            )
        )
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_keypoint_matches(
    image_a: np.ndarray, image_b: np.ndarray, rows: list[dict], path: str, title: str = '', max_lines: int = 300
) -> None:
    """Write a PNG with one row per keypoint pipeline: RGB images side by side, the pipeline's
    RANSAC inliers linked (green) and, when given, its region boxes outlined.

    rows: dicts with 'label', 'query' / 'map' (reloc.Keypoints), 'result' (reloc.RelocResult) and
    optional 'query_boxes' / 'map_boxes' (M, 4) x0, y0, x1, y1."""
    ha, wa = image_a.shape[:2]
    hb, wb = image_b.shape[:2]
    canvas = np.zeros((max(ha, hb), wa + wb, 3), np.uint8)
    canvas[:ha, :wa], canvas[:hb, wa:] = image_a, image_b
    fig, axes = plt.subplots(len(rows), 1, figsize=(12, 4.8 * len(rows)), dpi=110, squeeze=False)
    for ax, row in zip(axes[:, 0], rows):
        ax.imshow(canvas)
        for key, dx in (('query_boxes', 0), ('map_boxes', wa)):
            for x0, y0, x1, y1 in np.asarray(row.get(key, np.zeros((0, 4)))):
                ax.add_patch(Rectangle((x0 + dx, y0), x1 - x0, y1 - y0, fill=False, lw=0.8, ec='yellow', alpha=0.6))
        r = row['result']
        qi = r.matches.query_index[r.inlier_mask][:max_lines]
        mi = r.matches.map_index[r.inlier_mask][:max_lines]
        pa, pb = row['query'].uv[qi], row['map'].uv[mi]
        for (ua, va), (ub, vb) in zip(pa, pb):
            ax.plot([ua, ub + wa], [va, vb], '-', color='lime', lw=0.7, alpha=0.8)
        ax.scatter(row['query'].uv[:, 0], row['query'].uv[:, 1], s=2, c='red', alpha=0.5)
        ax.scatter(row['map'].uv[:, 0] + wa, row['map'].uv[:, 1], s=2, c='red', alpha=0.5)
        status = 'verified' if r.verified else f'not verified: {r.reason}'
        ax.set_title(f'{row["label"]}: {r.inliers} inliers / {len(r.matches)} matches ({status})', fontsize=9)
        ax.set_xlim(0, wa + wb)
        ax.set_ylim(canvas.shape[0], 0)
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
