"""Pictures of landmark matches: two images side by side, activation heatmaps, linked regions."""
from __future__ import annotations

import cv2
import matplotlib

matplotlib.use('Agg')  # files only; nodes and CI have no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import ConnectionPatch, Rectangle  # noqa: E402

from .landmarks import LandmarkSet  # noqa: E402


def heatmap(activation: np.ndarray, size: tuple) -> np.ndarray:
    """Activation (rows, cols) -> float (H, W) in [0, 1], bilinearly upsampled to size=(W, H)."""
    a = np.asarray(activation, np.float32)
    span = float(a.max() - a.min())
    a = (a - a.min()) / span if span > 0 else np.zeros_like(a)
    return cv2.resize(a, tuple(int(v) for v in size), interpolation=cv2.INTER_LINEAR)


def heatmap_bgr(image_rgb: np.ndarray, activation: np.ndarray, alpha: float = 0.5) -> np.ndarray:
    """The image blended with a JET heatmap of its activation, as BGR uint8 (for ROS `activation`)."""
    h, w = image_rgb.shape[:2]
    heat = cv2.applyColorMap((heatmap(activation, (w, h)) * 255).astype(np.uint8), cv2.COLORMAP_JET)
    return cv2.addWeighted(cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), 1 - alpha, heat, alpha, 0)


def plot_matches(image_a: np.ndarray, image_b: np.ndarray, a: LandmarkSet, b: LandmarkSet,
                 pairs: dict, path: str, title: str = '', max_links: int = 60) -> None:
    """Write a PNG: RGB images side by side with activation overlays, every landmark outlined,
    mutual pairs linked, line opacity = offset weight."""
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.8), dpi=110)
    for ax, img, s in ((axes[0], image_a, a), (axes[1], image_b, b)):
        ax.imshow(img)
        if s.activation is not None:
            heat = heatmap(s.activation, (img.shape[1], img.shape[0]))
            ax.imshow(heat, cmap='jet', alpha=0.5 * heat)  # transparent where the head is silent
        for (u, v) in s.centers:
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
        fig.add_artist(ConnectionPatch(xyA=tuple(a.centers[qa]), coordsA=axes[0].transData,
                                       xyB=tuple(b.centers[mb]), coordsB=axes[1].transData,
                                       color=colour, lw=1.0, alpha=max(0.15, wgt)))
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
