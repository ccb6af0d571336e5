"""Match overlays drawn with OpenCV (no matplotlib, so a node can draw at frame rate): the query
beside its best keyframe, matched regions outlined and linked, as `lln-match --plot` draws them.

    canvas = draw_match_overlay(query_bgr, keyframe_bgr, matches, caption=['query 12.3 s', ...])

`matches` is the matcher's `matches` table (lln_ros.ros.msgs.cloud_to_matches): query_u, query_v, map_u,
map_v, cell_w, cell_h (pixels of each image), similarity, weight. Line colour = similarity
(viridis, dark = low), thick lines = pairs consistent with the offset mode (weight >= 0.5).
The panels are labelled (query / map keyframe) and a key strip under them gives the similarity
colour scale and what the thick and thin lines mean. Images are BGR uint8 (H, W, 3).
"""

from __future__ import annotations

import cv2
import numpy as np

PANEL_HEIGHT = 360  # each image is scaled to this height on the canvas
CAPTION_HEIGHT = 22  # pixels per caption line above the images
LEGEND_HEIGHT = 24  # the key strip under the images
PANEL_LABELS = ('query', 'map keyframe')


def _fit(image: np.ndarray | None, height: int, original_height: int | None) -> tuple[np.ndarray, float]:
    """(image scaled to `height`, factor from original pixels to canvas pixels); a grey 4:3 panel
    when the image is unknown. original_height: of the image the coordinates refer to, when
    `image` is a thumbnail of it."""
    if image is None:
        return np.full((height, height * 4 // 3, 3), 64, np.uint8), 0.0
    if image.ndim == 2:
        image = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    scale = height / image.shape[0]
    fitted = cv2.resize(image, (max(1, round(image.shape[1] * scale)), height), interpolation=cv2.INTER_AREA)
    return fitted, height / (original_height or image.shape[0])


def similarity_colours(similarity: np.ndarray) -> np.ndarray:
    """(M,) cosine similarities -> (M, 3) BGR uint8 from the viridis map (0 -> dark blue, 1 -> yellow)."""
    level = np.clip(np.asarray(similarity, np.float32), 0, 1) * 255
    return cv2.applyColorMap(level.astype(np.uint8).reshape(-1, 1), cv2.COLORMAP_VIRIDIS).reshape(-1, 3)


def draw_match_overlay(
    query: np.ndarray,
    keyframe: np.ndarray | None,
    matches: np.ndarray,
    caption: list[str] = (),
    max_links: int = 60,
    height: int = PANEL_HEIGHT,
    original_heights: tuple = (None, None),
) -> np.ndarray:
    """BGR uint8 canvas (CAPTION_HEIGHT * len(caption) + height + LEGEND_HEIGHT, Wq + Wk, 3): query
    left, keyframe right, each labelled in its top-left corner, the key strip at the bottom.

    keyframe None (its image was never seen, e.g. a map built by another run): a grey panel that
    says so, and the query's matched regions are still outlined. At most `max_links` pairs are drawn,
    the highest weight * similarity first. original_heights: (query, keyframe) heights in pixels of
    the images the match coordinates refer to, when thumbnails are drawn (None = the image's own).
    """
    left, sq = _fit(query, height, original_heights[0])
    right, sk = _fit(keyframe, height, original_heights[1])
    top = CAPTION_HEIGHT * len(caption)
    canvas = np.zeros((top + height + LEGEND_HEIGHT, left.shape[1] + right.shape[1], 3), np.uint8)
    canvas[top : top + height, : left.shape[1]] = left
    canvas[top : top + height, left.shape[1] :] = right
    dx = left.shape[1]
    draw_key(canvas[top + height :])
    if keyframe is None:
        cv2.putText(
            canvas,
            'keyframe image not seen',
            (dx + 10, top + height // 2),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.6,
            (220, 220, 220),
            1,
            cv2.LINE_AA,
        )
    for i, line in enumerate(caption):
        cv2.putText(
            canvas,
            line,
            (6, CAPTION_HEIGHT * (i + 1) - 6),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.55,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    if len(matches) == 0:
        label_panels(canvas, top, dx)
        return canvas
    order = np.argsort(-(matches['weight'] * matches['similarity']))[:max_links]
    colours = similarity_colours(matches['similarity'])
    for j in order[::-1]:  # the strongest links last, so they are drawn on top
        m = matches[j]
        colour = tuple(int(c) for c in colours[j])
        thickness = 2 if m['weight'] >= 0.5 else 1  # consistent with the offset mode, or not
        q = (m['query_u'] * sq, top + m['query_v'] * sq)
        half = (m['cell_w'] * sq / 2, m['cell_h'] * sq / 2)
        cv2.rectangle(
            canvas,
            (round(q[0] - half[0]), round(q[1] - half[1])),
            (round(q[0] + half[0]), round(q[1] + half[1])),
            colour,
            1,
            cv2.LINE_AA,
        )
        if keyframe is None:
            continue
        k = (dx + m['map_u'] * sk, top + m['map_v'] * sk)
        half = (m['cell_w'] * sk / 2, m['cell_h'] * sk / 2)
        cv2.rectangle(
            canvas,
            (round(k[0] - half[0]), round(k[1] - half[1])),
            (round(k[0] + half[0]), round(k[1] + half[1])),
            colour,
            1,
            cv2.LINE_AA,
        )
        cv2.line(canvas, (round(q[0]), round(q[1])), (round(k[0]), round(k[1])), colour, thickness, cv2.LINE_AA)
        for end in (q, k):
            cv2.circle(canvas, (round(end[0]), round(end[1])), 3, colour, -1, cv2.LINE_AA)
    label_panels(canvas, top, dx)
    return canvas


def _text(canvas: np.ndarray, text: str, origin: tuple, scale: float = 0.45) -> int:
    """White text on a dark box at origin (left, baseline); returns the x after it."""
    (w, h), base = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    x, y = origin
    cv2.rectangle(canvas, (x - 2, y - h - 3), (x + w + 2, y + base), (0, 0, 0), -1)
    cv2.putText(canvas, text, (x, y), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return x + w


def label_panels(canvas: np.ndarray, top: int, dx: int) -> None:
    """'query' and 'map keyframe' in the top-left corners of the two panels (drawn last: on top)."""
    for x, label in zip((4, dx + 4), PANEL_LABELS):
        _text(canvas, label, (x, top + 16))


def draw_key(strip: np.ndarray) -> None:
    """The key under the images, in place: the similarity colour bar 0..1 and the line styles."""
    h = strip.shape[0]
    x = _text(strip, 'similarity 0', (4, h - 8)) + 6
    bar = similarity_colours(np.linspace(0, 1, 100))
    for i, colour in enumerate(bar):
        cv2.line(strip, (x + i, 5), (x + i, h - 6), tuple(int(c) for c in colour), 1)
    x = _text(strip, '1', (x + len(bar) + 4, h - 8)) + 14
    cv2.line(strip, (x, h // 2), (x + 20, h // 2), (200, 200, 200), 2, cv2.LINE_AA)
    x = _text(strip, 'offset-consistent pair', (x + 26, h - 8)) + 14
    cv2.line(strip, (x, h // 2), (x + 20, h // 2), (200, 200, 200), 1, cv2.LINE_AA)
    _text(strip, 'other mutual pair (boxes: the matched regions)', (x + 26, h - 8))
