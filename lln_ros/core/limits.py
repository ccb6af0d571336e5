"""Input limits of the nodes and the model record check: what a message may ask of a node.

A ROS message is built by someone else. Every size it declares (image width and height, landmark
rows, descriptor length D, cell size, keypoint rows) is checked against these limits before
anything is allocated or computed from it, so one message can cost a node at most a bounded
amount of memory and time. The nodes declare each limit as a parameter whose default comes from
`default_conf` (the one source of the defaults); violations raise LimitError, which the nodes
count as a refused message (bad_image / bad_keyframe / bad_query / bad_keypoints).

    validate_model(model) -> dict            # Extractor.model_info / a map's model record
    parse_model_json(text) -> object          # model_info text, size- and depth-bounded, then json.loads
    stamp_problem(sec, nanosec) -> str        # '' when a stamp fits every type it is written to
    check_landmark_set(lset, model, conf)     # declared sizes of a decoded landmark set
    check_pixels(width, height, conf, what)   # an image, before it is decoded or copied

No rclpy here: the node, both map backends and lln-map use these functions.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from ..errors import MessageError, ModelError

GRID_STRIDE = 32  # every backbone here has a stride-32 feature grid (lln_ros.io.image)

default_conf = {
    # raw and decoded images (extractor) and an image size declared by a landmark cloud (matcher):
    # 32 MiP = 8192 x 4096; an RGB copy of such an image is 96 MiB
    'max_image_pixels': 33_554_432,
    # landmark rows per set (keyframe or query); method 'all' at input_height 288 gives at most 9 x 128
    'max_landmarks': 4096,
    # descriptor size D (resnet101 layer4 is 2048)
    'max_descriptor_dim': 4096,
    # feature-grid rows and columns a landmark set may declare (image size / cell size): the network
    # input is at most 4096 px wide (lln_ros.io.image.MAX_WIDTH), i.e. 128 cells of 32 px; the height is
    # the model's input_height / 32 when the model says it
    'max_grid_side': 128,
    # ORB keypoint rows per keypoints cloud (the extractor's keypoints_max is 500 by default)
    'max_keypoints': 20_000,
    # PointFields per cloud: every table here has at most 11 (candidates with inliers and
    # sequence_score); 40,000 fields once stalled the decoder for 15 s (issue 25)
    'max_point_fields': 64,
}

# A stamp travels as builtin_interfaces/Time (int32 sec, uint32 nanosec) and is written back as the
# candidates' stamp_sec (INT32) and stamp_nanosec (UINT32), and into the map (SQLite INTEGER, Milvus
# INT64). The narrowest of them bounds it; nanosec must be normalised (< 1e9): a stamp is refused,
# never renormalised, so an answer's stamps are exactly the sender's.
STAMP_SEC_RANGE = (-(2**31), 2**31 - 1)
KEYFRAME_ID_MAX = 2**32 - 1  # the candidates' and matches' keyframe_id is UINT32
NANOSEC_PER_SEC = 1_000_000_000

# model_info (and a map's model record) is a small flat JSON object (Extractor.model_info: depth 2,
# ~20 keys). Anything far larger or deeper is refused before it is parsed further or recorded:
# a 2 KB list nested 1,000 deep raised RecursionError past the handler on every restart (issue 25)
MODEL_JSON_MAX_BYTES = 65_536
MODEL_JSON_MAX_DEPTH = 8
MODEL_JSON_MAX_ITEMS = 4_096  # values (keys, list items, scalars) in the whole document


class LimitError(MessageError):
    """A message that declares more than a limit allows (refused before anything is sized by it)."""


def limits(conf: Mapping | None = None) -> dict:
    """default_conf updated by conf; every value a positive integer (ValueError otherwise)."""
    out = {**default_conf, **(conf or {})}
    unknown = sorted(set(out) - set(default_conf))
    if unknown:
        raise ValueError(f'unknown limit(s) {unknown}; known: {sorted(default_conf)}')
    for name, value in out.items():
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f'limit {name} must be a positive integer, got {value!r}')
    return out


def stamp_problem(sec, nanosec) -> str:
    """'' when (sec, nanosec) fits every type a stamp is written to (STAMP_SEC_RANGE, nanosec in
    [0, 1e9)); else the reason, for a MessageError or a quarantine note."""
    try:
        sec, nanosec = int(sec), int(nanosec)
    except (TypeError, ValueError, OverflowError):
        return f'stamp ({sec!r}, {nanosec!r}) is not a pair of integers'
    low, high = STAMP_SEC_RANGE
    if not low <= sec <= high:
        return f'stamp sec {sec} does not fit int32 [{low}, {high}] (builtin_interfaces/Time, candidates stamp_sec)'
    if not 0 <= nanosec < NANOSEC_PER_SEC:
        return f'stamp nanosec {nanosec} is not in [0, 1e9) (refused, not renormalised)'
    return ''


def json_shape_problem(value, max_depth: int = MODEL_JSON_MAX_DEPTH, max_items: int = MODEL_JSON_MAX_ITEMS) -> str:
    """'' when a parsed JSON value nests at most max_depth containers and holds at most max_items
    values; else the reason. Iterative: a deep value cannot exhaust the Python stack here."""
    stack, items = [(value, 1)], 0
    while stack:
        node, depth = stack.pop()
        items += 1
        if items > max_items:
            return f'more than {max_items} values'
        if isinstance(node, (dict, list)):
            if depth > max_depth:
                return f'nested more than {max_depth} deep'
            children = node.values() if isinstance(node, dict) else node
            stack.extend((child, depth + 1) for child in children)
            items += len(node) if isinstance(node, dict) else 0  # the keys
    return ''


def parse_model_json(text, what: str = 'model_info'):
    """json.loads of a model record, bounded: ModelError (a ValueError) for text longer than
    MODEL_JSON_MAX_BYTES, nesting deeper than MODEL_JSON_MAX_DEPTH (checked on the raw text before
    parsing, so the parser's own recursion is never reached), or more than MODEL_JSON_MAX_ITEMS
    values. Then validate_model decides whether it is a model."""
    if isinstance(text, (bytes, bytearray)):
        text = bytes(text).decode('utf-8', errors='replace')
    if not isinstance(text, str):
        raise ModelError(f'{what} must be JSON text, got {type(text).__name__}')
    if len(text) > MODEL_JSON_MAX_BYTES:
        raise ModelError(f'{what} is {len(text)} characters, more than {MODEL_JSON_MAX_BYTES}')
    if _bracket_depth(text) > MODEL_JSON_MAX_DEPTH:
        raise ModelError(f'{what} is nested more than {MODEL_JSON_MAX_DEPTH} deep')
    import json

    try:
        value = json.loads(text)
    except RecursionError:  # not reachable after the depth check; kept as a ModelError all the same
        raise ModelError(f'{what} is nested too deep to parse') from None
    problem = json_shape_problem(value)
    if problem:
        raise ModelError(f'{what} is {problem}')
    return value


def _bracket_depth(text: str) -> int:
    """Deepest [ / { nesting of JSON text, outside strings (a linear scan)."""
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == '\\':
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in '[{':
            depth += 1
            deepest = max(deepest, depth)
        elif ch in ']}':
            depth -= 1
    return deepest


def _int_field(model: Mapping, name: str, low: int, high: int, required: bool) -> int | None:
    value = model.get(name)
    if value is None:
        if required:
            raise ModelError(f'model has no {name}')
        return None
    # JSON numbers arrive as int or float (1e999 is inf, 1e30 is a float); bool is an int in Python
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or (isinstance(value, float) and not (math.isfinite(value) and value.is_integer()))
    ):
        raise ModelError(f'model {name} must be an integer, got {value!r}')
    value = int(value)
    if not low <= value <= high:
        raise ModelError(f'model {name} is {value}; it must be in [{low}, {high}]')
    return value


def validate_model(model, conf: Mapping | None = None) -> dict:
    """A copy of `model` (Extractor.model_info, a map's model record, or {descriptor_space,
    descriptor_dim}) with descriptor_dim (and input_height, when present) as ints, after checking
    every field the code relies on. Raises ModelError naming the first problem:

    descriptor_space  a non-empty string of at most 256 characters; when it ends in '/D' with D a
                      number (backbone/layer/D), D must equal descriptor_dim
    descriptor_dim    an integer in [1, max_descriptor_dim]
    input_height      optional; an integer multiple of 32 in [32, 32 * max_grid_side]
    """
    lim = limits(conf)
    problem = json_shape_problem(model)
    if problem:  # a dict built in Python can nest as deep as text can: checked here too
        raise ModelError(f'model is {problem}')
    if not isinstance(model, Mapping):
        raise ModelError(
            f'model must be a JSON object with descriptor_space and descriptor_dim '
            f'(Extractor.model_info), got {type(model).__name__}'
        )
    space = model.get('descriptor_space')
    if not isinstance(space, str) or not space or len(space) > 256:
        raise ModelError(
            f'model descriptor_space must be a non-empty string of at most 256 characters, got {_short(space)}'
        )
    dim = _int_field(model, 'descriptor_dim', 1, lim['max_descriptor_dim'], required=True)
    tail = space.rsplit('/', 1)[-1]
    if '/' in space and tail.isdigit() and int(tail) != dim:
        raise ModelError(f'model descriptor_space {space!r} ends in D={tail} but descriptor_dim is {dim}')
    height = _int_field(model, 'input_height', GRID_STRIDE, GRID_STRIDE * lim['max_grid_side'], required=False)
    if height is not None and height % GRID_STRIDE:
        raise ModelError(f'model input_height is {height}; it must be a multiple of {GRID_STRIDE}')
    out = dict(model)
    out['descriptor_dim'] = dim
    if height is not None:
        out['input_height'] = height
    return out


def _short(value, n: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= n else text[:n] + '...'


def check_pixels(width: int, height: int, conf: Mapping, what: str = 'image') -> None:
    """LimitError when a width x height image exceeds max_image_pixels (Python ints: no overflow)."""
    pixels = int(width) * int(height)
    if pixels > conf['max_image_pixels']:
        raise LimitError(
            f'{what}: {int(width)}x{int(height)} = {pixels} pixels is more than max_image_pixels '
            f'{conf["max_image_pixels"]}'
        )


def check_landmark_set(lset, model: Mapping | None, conf: Mapping, what: str = 'landmarks cloud') -> None:
    """The sizes a decoded landmark set declares, against the limits and the model.

    image_size within max_image_pixels; landmark count within max_landmarks; the grid
    (image_size / cell_size) made of whole cells (within 1%), at most max_grid_side cells a side,
    and max_grid_side rows, or exactly input_height / 32 rows when the model says its input_height.
    These are what the matcher's similarity and the map store size their work by."""
    image_w, image_h = (float(v) for v in lset.image_size)
    cell_w, cell_h = (float(v) for v in lset.cell_size)
    if not all(math.isfinite(v) and v > 0 for v in (image_w, image_h, cell_w, cell_h)):
        raise LimitError(
            f'{what}: sizes must be positive and finite (image {image_w:g}x{image_h:g}, cell {cell_w:g}x{cell_h:g})'
        )
    if image_w * image_h > conf['max_image_pixels']:
        raise LimitError(
            f'{what}: declared image {image_w:g}x{image_h:g} is more than max_image_pixels {conf["max_image_pixels"]}'
        )
    if len(lset) > conf['max_landmarks']:
        raise LimitError(f'{what}: {len(lset)} landmarks is more than max_landmarks {conf["max_landmarks"]}')
    cols, rows = image_w / cell_w, image_h / cell_h
    side = conf['max_grid_side']
    if cols > side + 0.5 or rows > side + 0.5:
        raise LimitError(
            f'{what}: image {image_w:g}x{image_h:g} in cells of {cell_w:g}x{cell_h:g} is a '
            f'{cols:.4g}x{rows:.4g} grid; at most {side} cells a side (max_grid_side)'
        )
    if abs(cols - round(cols)) > 0.01 or abs(rows - round(rows)) > 0.01 or round(cols) < 1 or round(rows) < 1:
        raise LimitError(
            f'{what}: image {image_w:g}x{image_h:g} is not a whole number of '
            f'{cell_w:g}x{cell_h:g} cells ({cols:.4g}x{rows:.4g})'
        )
    height = (model or {}).get('input_height')
    if height and round(rows) != int(height) // GRID_STRIDE:
        raise LimitError(
            f'{what}: grid of {round(rows)} rows, but the model (input_height {height}) '
            f'makes {int(height) // GRID_STRIDE}'
        )
    if tuple(int(v) for v in lset.grid) != (round(rows), round(cols)):
        raise LimitError(
            f'{what}: grid {tuple(lset.grid)} does not match image / cell size ({round(rows)}, {round(cols)})'
        )


def height_change(before: dict, model: dict) -> str:
    """What to say, once per change, when a model_info of the same descriptor space as `before` (the
    previous model_info, else the map's record) brings another input_height: every landmark cloud of
    the old height is refused from then on (bad_query / bad_keyframe: grid rows). '' = nothing to say."""
    old, new = before.get('input_height'), model.get('input_height')
    if old is None or new is None or int(old) == int(new):
        return ''
    if before.get('descriptor_space') != model.get('descriptor_space'):
        return ''  # another model: the map's own refusal (use_model) says so
    return (
        f'model_info of the same model {model["descriptor_space"]!r} changes input_height from '
        f'{int(old)} to {int(new)}: landmark clouds must now have a grid of {int(new) // 32} rows, '
        f'so clouds of an extractor still at input_height {int(old)} ({int(old) // 32} rows) are '
        f'refused as bad_query / bad_keyframe until the extractor and its model_info agree'
    )
