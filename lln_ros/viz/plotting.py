"""Pictures of landmark matches: two images side by side, activation heatmaps, linked regions.

Every mark drawn has a legend entry and every colour scale a colour bar: a newcomer reads the
picture without the code. The left panel is the query, the right one the map image (labels=).
"""

from __future__ import annotations

import matplotlib

matplotlib.use('Agg')  # files only; nodes and CI have no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.cm import ScalarMappable  # noqa: E402
from matplotlib.colors import Normalize  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import ConnectionPatch, Patch, Rectangle  # noqa: E402

from ..core.landmarks import LandmarkSet  # noqa: E402
from ..io.image import heatmap  # noqa: E402

SIMILARITY_CMAP = 'viridis'  # matched pairs: cosine similarity of the two landmark descriptors
ACTIVATION_CMAP = 'jet'  # score maps: the LLN head's activation (or the feature norm)


def plot_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    a: LandmarkSet,
    b: LandmarkSet,
    pairs: dict,
    path: str,
    title: str = '',
    max_links: int = 60,
    labels: tuple[str, str] = ('query', 'map'),
) -> None:
    """Write a PNG: RGB images side by side (labels: the panels' titles) with activation overlays,
    every landmark outlined, mutual pairs linked, line colour = similarity, opacity = offset weight;
    a legend for the marks and colour bars for both colour scales under the images."""
    # the image row as tall as the wider-than-tall panels need (no blank band above the key)
    aspect = max(image_a.shape[0] / image_a.shape[1], image_b.shape[0] / image_b.shape[1])
    image_h = 5.9 * aspect
    title_h = 0.25 + 0.2 * (title.count('\n') + 1) if title else 0.1  # inches above the panel titles
    fig_h = image_h + 1.2 + title_h
    fig = plt.figure(figsize=(12, fig_h), dpi=110)
    # the images on top; under them the key, the similarity colour bar and the score colour bar
    rows = fig.add_gridspec(2, 1, height_ratios=[image_h, 0.3], hspace=0.45 / ((image_h + 0.3) / 2))
    rows.update(top=1 - title_h / fig_h, bottom=0.1)
    top = rows[0].subgridspec(1, 2, wspace=0.04)
    bottom = rows[1].subgridspec(1, 3, width_ratios=[1.15, 1, 1], wspace=0.15)
    axes = [fig.add_subplot(top[0, 0]), fig.add_subplot(top[0, 1])]
    has_heat = False
    for ax, img, s, label in ((axes[0], image_a, a, labels[0]), (axes[1], image_b, b, labels[1])):
        ax.imshow(img)
        if s.activation is not None:
            heat = heatmap(s.activation, (img.shape[1], img.shape[0]))
            ax.imshow(heat, cmap=ACTIVATION_CMAP, alpha=0.5 * heat)  # transparent where the head is silent
            has_heat = True
        for u, v in s.centers:
            w, h = s.cell_size
            ax.add_patch(Rectangle((u - w / 2, v - h / 2), w, h, fill=False, lw=0.5, ec='white', alpha=0.5))
        ax.set_title(label, fontsize=10, loc='left')
        ax.set_axis_off()
    order = np.argsort(-pairs['weight'] * pairs['similarity'])[:max_links]
    cmap = plt.get_cmap(SIMILARITY_CMAP)
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
    shown = min(len(order), max_links)
    handles = [
        Patch(fill=False, ec='grey', lw=0.8, label='a selected landmark (grid cell)'),
        Patch(fill=False, ec=cmap(0.8), lw=1.5, label='a landmark in a mutual pair'),
        Line2D([], [], color=cmap(0.8), lw=1.0, label=f'mutual pair ({shown} strongest; faint = off the offset mode)'),
    ]
    key = fig.add_subplot(bottom[0, 0])
    key.set_axis_off()
    key.legend(handles=handles, loc='center left', fontsize=8, frameon=False)
    fig.colorbar(
        ScalarMappable(Normalize(0, 1), cmap),
        cax=fig.add_subplot(bottom[0, 1]),
        orientation='horizontal',
        label='pair similarity (descriptor cosine)',
    )
    if has_heat:
        fig.colorbar(
            ScalarMappable(Normalize(0, 1), ACTIVATION_CMAP),
            cax=fig.add_subplot(bottom[0, 2]),
            orientation='horizontal',
            label='tint: LLN activation / its max per image',
        )
    if title:
        fig.suptitle(title, fontsize=10, y=1 - 0.1 / fig_h, va='top')
    fig.savefig(path, bbox_inches='tight')
    plt.close(fig)


def plot_keypoint_matches(
    image_a: np.ndarray,
    image_b: np.ndarray,
    rows: list[dict],
    path: str,
    title: str = '',
    max_lines: int = 300,
    labels: tuple[str, str] = ('query', 'map'),
) -> None:
    """Write a PNG with one row per keypoint pipeline: RGB images side by side (query left, map
    right), the pipeline's RANSAC inliers linked (green), every keypoint a red dot and, when given,
    its region boxes outlined (yellow); a legend names the three.

    rows: dicts with 'label', 'query' / 'map' (reloc.Keypoints), 'result' (reloc.RelocResult) and
    optional 'query_boxes' / 'map_boxes' (M, 4) x0, y0, x1, y1."""
    ha, wa = image_a.shape[:2]
    hb, wb = image_b.shape[:2]
    canvas = np.zeros((max(ha, hb), wa + wb, 3), np.uint8)
    canvas[:ha, :wa], canvas[:hb, wa:] = image_a, image_b
    fig, axes = plt.subplots(len(rows), 1, figsize=(12, 4.8 * len(rows) + 0.6), dpi=110, squeeze=False)
    boxes = any(len(np.asarray(row.get(key, []))) for row in rows for key in ('query_boxes', 'map_boxes'))
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
        for x, text in ((4, labels[0]), (wa + 4, labels[1])):
            ax.text(x, 4, text, color='white', fontsize=9, va='top', bbox={'fc': 'black', 'alpha': 0.6, 'lw': 0})
        ax.set_xlim(0, wa + wb)
        ax.set_ylim(canvas.shape[0], 0)
        ax.set_axis_off()
    handles = [
        Line2D([], [], ls='', marker='o', ms=3, color='red', label='a keypoint'),
        Line2D([], [], color='lime', lw=1.0, label=f'a RANSAC inlier match (at most {max_lines} drawn)'),
    ]
    if boxes:
        handles.append(Patch(fill=False, ec='yellow', lw=0.8, label='a matched landmark region (the mLLN search area)'))
    fig.legend(handles=handles, loc='lower center', ncol=len(handles), fontsize=8, frameon=False)
    if title:
        fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    fig.savefig(path)
    plt.close(fig)
