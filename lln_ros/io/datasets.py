"""Place-recognition datasets: which reference images are correct answers for which queries.

Every reader returns a `Dataset`:

    ref_paths, query_paths   image files (natural sort order: 2.jpg before 10.jpg)
    gt          (Q, R) bool  ref r is a correct answer for query q
    candidates  (Q, R) bool or None   which refs query q may be answered with (loop protocol)
    sequence    bool         queries and references are each ordered along one route, so a sequence
                             search (lln-eval --sequence, seqslam) means something; False for
                             collections of unrelated places (VPR-Bench webcams, photo pairs)
    info        dict         what was dropped or clipped, and why

Formats: aligned traverses (two folders, same index = same place, +-tol), VPR-Bench
(DIR/query, DIR/ref, DIR/ground_truth_new.npy), a loop sequence (one folder, NxN ground-truth
matrix), a sequence with camera poses (TUM RGB-D: same place from relative pose), and the Gardens
Point Walking archive layout. Everything is checked (folders, lengths,
ground-truth shape, every image decodes) before any long computation starts.
"""

from __future__ import annotations

import hashlib
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ..errors import DatasetError

IMAGE_SUFFIXES = ('.jpg', '.jpeg', '.png', '.bmp', '.tif', '.tiff', '.ppm', '.pgm', '.webp')
BLANK_STD = 2.0  # grey-level standard deviation below which a frame is flat (drop=flat)
# drop=blank: at most this many grey levels between the 5th and 95th percentile. Robust to a small
# overlay (Nordland's channel logo covers ~1% of a tunnel frame and lifts its std to ~2.9)
BLANK_SPREAD = 2.0
DROP_MODES = {
    'flat': f'grey std below {BLANK_STD:g}',
    'blank': f'5-95 percentile grey spread at most {BLANK_SPREAD:g}, or flat',
    'frozen': 'pixel-identical to the query frame before it (a stalled camera; the first of a run stays)',
}


@dataclass
class Dataset:
    name: str
    ref_paths: list
    query_paths: list
    gt: np.ndarray
    candidates: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    sequence: bool = True

    @property
    def queries_with_match(self) -> int:
        return int(self.gt.any(1).sum())


def natural_key(path: str | os.PathLike) -> list:
    """Sort key that orders 2.jpg before 10.jpg (digit runs compare as numbers)."""
    name = Path(path).name
    return [(0, int(tok), '') if tok.isdigit() else (1, 0, tok.lower()) for tok in re.split(r'(\d+)', name)]


def image_keys(paths) -> list[str]:
    """One short key per image path: a digest of its last three path components (for example
    nordland_trimmed/summer/00001.png), so the same file has the same key on every machine, whatever
    folder the data sits in. A checkpoint lists the keys of the images it was trained and validated
    on; lln-eval compares them with a dataset's to say whether the dataset is held out for a head."""
    return sorted({hashlib.blake2b('/'.join(Path(p).parts[-3:]).encode(), digest_size=8).hexdigest() for p in paths})


def list_images(folder: str | os.PathLike, pattern: str | None = None) -> list[Path]:
    """Image files of a folder (not recursive), in natural order; with `pattern` (a glob such as
    '*.jpg') only the matching ones. DatasetError when the folder is missing or holds no images.

    Mind folders that hold other images beside the frames: rtabmap_loop/ has samples_GT.bmp."""
    folder = Path(folder)
    if not folder.exists():
        raise DatasetError(f'image folder {folder} does not exist')
    if not folder.is_dir():
        raise DatasetError(f'{folder} is not a folder')
    files = folder.glob(pattern) if pattern else folder.iterdir()
    paths = sorted((p for p in files if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES), key=natural_key)
    if not paths:
        what = f'images matching {pattern!r}' if pattern else f'images ({", ".join(IMAGE_SUFFIXES)})'
        raise DatasetError(f'image folder {folder} holds no {what}')
    return paths


def read_checked(paths: list, content: bool = False) -> list[tuple]:
    """(width, height, grey std) of every image; DatasetError naming the first that does not decode.
    content: also the 5-95 percentile grey spread and a digest of the pixels (drop=blank, frozen)."""
    out = []
    for p in paths:
        im = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if im is None or im.size == 0:
            raise DatasetError(f'cannot read image {p} (not an image, or truncated)')
        stats = (im.shape[1], im.shape[0], float(im.std()))
        if content:
            lo, hi = np.percentile(im, (5, 95))
            stats += (
                float(hi - lo),
                hashlib.blake2b(im.tobytes() + np.asarray(im.shape, np.int64).tobytes(), digest_size=16).digest(),
            )
        out.append(stats)
    return out


def parse_drop(drop) -> tuple[str, ...]:
    """'blank+frozen' | 'none' | ('blank', 'frozen') -> the drop modes, checked against DROP_MODES."""
    modes = drop.split('+') if isinstance(drop, str) else list(drop)
    modes = tuple(m.strip() for m in modes if m.strip() and m.strip() != 'none')
    bad = [m for m in modes if m not in DROP_MODES]
    if bad:
        raise DatasetError(f'drop= takes none or a +-joined subset of {"+".join(DROP_MODES)}, got {bad[0]!r}')
    return modes


def dropped_frames(stats: list[tuple], modes: tuple[str, ...]) -> dict[str, np.ndarray]:
    """{mode: (N,) bool} the frames each drop mode removes, from read_checked(..., content=True)."""
    std = np.array([s[2] for s in stats])
    out = {'flat': std < BLANK_STD}
    if 'blank' in modes:
        out['blank'] = out['flat'] | (np.array([s[3] for s in stats]) <= BLANK_SPREAD)
    if 'frozen' in modes:
        same = np.array([i > 0 and stats[i][4] == stats[i - 1][4] for i in range(len(stats))], bool)
        out['frozen'] = same & ~out.get('blank', out['flat'])  # a repeated blank frame counts as blank
    return {m: out[m] for m in modes}


def parse_range(text: str | None):
    """'START:END' fractions of a route (e.g. '0.7:1', the last 30%) -> (start, end), or None."""
    if not text:
        return None
    try:
        start, end = (float(v) for v in text.split(':'))
    except ValueError:
        raise DatasetError(f'--range must be START:END fractions such as 0.7:1, got {text!r}') from None
    if not 0 <= start < end <= 1:
        raise DatasetError(f'--range needs 0 <= START < END <= 1, got {text!r}')
    return start, end


def _select(n: int, frac) -> slice:
    if frac is None:
        return slice(0, n)
    start, end = frac
    if not 0 <= start < end <= 1:
        raise DatasetError(f'range must satisfy 0 <= start < end <= 1, got {frac}')
    return slice(int(round(start * n)), int(round(end * n)))


def aligned(
    dir_ref, dir_query, tol: int = 2, frac=None, name: str | None = None, drop='flat', sequence: bool = True
) -> Dataset:
    """Two traverses, same index = same place; a ref within +-tol frames is correct. `frac`
    (start, end) in [0, 1] keeps that contiguous part of the route. Query frames with no
    recognisable place are dropped by `drop` (DROP_MODES, '+'-joined or a tuple; 'none' keeps
    every frame); the counts are in info: blank_queries_dropped (flat or blank), frozen_queries_dropped.
    References are never dropped: blank_refs counts them by the same rule (blank with drop=blank, else flat)."""
    modes = parse_drop(drop)
    refs, queries = list_images(dir_ref), list_images(dir_query)
    if len(refs) != len(queries):
        raise DatasetError(
            f'aligned traverses differ in length: {dir_ref} has {len(refs)} images, {dir_query} has {len(queries)}'
        )
    part = _select(len(refs), frac)
    refs, queries = refs[part], queries[part]
    if not refs:
        raise DatasetError(f'range {frac} selects no frames of {len(list_images(dir_ref))}')
    ref_stats, query_stats = read_checked(refs, content=True), read_checked(queries, content=True)
    idx = np.arange(len(refs))
    drops = dropped_frames(query_stats, modes)
    keep = ~np.any(list(drops.values()), axis=0) if drops else np.ones(len(refs), bool)
    gt = np.abs(idx[keep][:, None] - idx[None, :]) <= int(tol)
    blank = drops.get('blank', drops.get('flat', np.zeros(len(refs), bool)))
    info = {
        'tol': int(tol),
        'range': list(frac) if frac else [0.0, 1.0],
        'first_index': part.start,
        'drop': '+'.join(modes) or 'none',
        'blank_queries_dropped': int(blank.sum()),
        'frozen_queries_dropped': int(drops['frozen'].sum()) if 'frozen' in drops else 0,
        # kept (a map keeps every frame), counted by the blank rule in use (flat without drop=blank)
        'blank_refs': int(dropped_frames(ref_stats, ('blank',) if 'blank' in modes else ('flat',)).popitem()[1].sum()),
        'ref_sizes': [s[:2] for s in ref_stats],
        'query_sizes': [s[:2] for s, k in zip(query_stats, keep) if k],
    }
    return Dataset(
        name or f'{Path(dir_ref).name}-vs-{Path(dir_query).name}',
        refs,
        [q for q, k in zip(queries, keep) if k],
        gt,
        None,
        info,
        bool(sequence),
    )


def vprbench(root, name: str | None = None, sequence: bool = False) -> Dataset:
    """DIR/query/*, DIR/ref/*, DIR/ground_truth_new.npy (rows [query_index, [ref indices]]).
    Ref indices past the end (the public Gardens Point file names 200 and 201) are clipped.
    Not a sequence by default: the layout holds webcams and photo pairs as well as routes (say
    sequence=True for a folder that is one route in file order)."""
    root = Path(root)
    refs, queries = list_images(root / 'ref'), list_images(root / 'query')
    gt = vprbench_gt(root / 'ground_truth_new.npy', len(queries), len(refs))
    ref_stats, query_stats = read_checked(refs), read_checked(queries)
    return Dataset(
        name or root.name,
        refs,
        queries,
        gt[0],
        None,
        {'clipped_refs': gt[1], 'ref_sizes': [s[:2] for s in ref_stats], 'query_sizes': [s[:2] for s in query_stats]},
        bool(sequence),
    )


def vprbench_gt(path, n_queries: int, n_refs: int) -> tuple[np.ndarray, int]:
    """(Q, R) bool from a VPR-Bench ground_truth_new.npy, and how many out-of-range refs were clipped."""
    if not Path(path).is_file():
        raise DatasetError(f'ground truth not found: {path}')
    try:
        rows = np.load(path, allow_pickle=True)
    except Exception as e:  # OSError, ValueError, UnpicklingError, EOFError ... for a bad file
        raise DatasetError(f'cannot read ground truth {path}: {e}') from e
    if rows.ndim != 2 or rows.shape[1] != 2:
        raise DatasetError(f'{path}: expected rows [query_index, [ref indices]] (shape (Q, 2)), got shape {rows.shape}')
    gt = np.zeros((n_queries, n_refs), bool)
    clipped = 0
    try:
        for row in rows:
            q, refs = int(row[0]), np.atleast_1d(np.asarray(row[1], np.int64))
            if not 0 <= q < n_queries:
                raise DatasetError(f'{path}: query index {q} outside 0..{n_queries - 1}')
            ok = (refs >= 0) & (refs < n_refs)
            clipped += int((~ok).sum())
            gt[q, refs[ok]] = True
    except (TypeError, IndexError, ValueError) as e:
        raise DatasetError(f'{path}: rows must be [query_index, [ref indices]]: {e}') from e
    return gt, clipped


def loop(folder, gt_file, min_gap: int = 10, name: str | None = None, sequence: bool = True) -> Dataset:
    """One ordered sequence and an NxN ground-truth matrix (image or .npy; nonzero at (r, c) = frame r
    revisits frame c). Query r may be answered only with frames at least min_gap older."""
    frames = list_images(folder)
    gt_file = Path(gt_file)
    frames = [f for f in frames if f.resolve() != gt_file.resolve()]
    if not gt_file.is_file():
        raise DatasetError(f'ground truth not found: {gt_file}')
    if gt_file.suffix.lower() == '.npy':
        try:
            matrix = np.load(gt_file)
        except Exception as e:  # a corrupt file, or pickled objects
            raise DatasetError(f'cannot read ground truth {gt_file} (expected a numeric NxN .npy): {e}') from e
        if not (np.issubdtype(matrix.dtype, np.number) or matrix.dtype == bool):
            raise DatasetError(f'ground truth {gt_file} must be numeric, got dtype {matrix.dtype}')
    else:
        matrix = cv2.imread(str(gt_file), cv2.IMREAD_GRAYSCALE)
        if matrix is None:
            raise DatasetError(f'cannot read ground-truth image {gt_file}')
    n = len(frames)
    if matrix.shape != (n, n):
        raise DatasetError(
            f'ground truth {gt_file} is {matrix.shape[0]}x{matrix.shape[1]}; the sequence in '
            f'{folder} has {n} frames, so it must be {n}x{n}'
        )
    stats = read_checked(frames)
    idx = np.arange(n)
    candidates = idx[None, :] <= idx[:, None] - int(min_gap)
    return Dataset(
        name or Path(folder).name,
        frames,
        frames,
        (matrix > 0) & candidates,
        candidates,
        {'min_gap': int(min_gap), 'ref_sizes': [s[:2] for s in stats], 'query_sizes': [s[:2] for s in stats]},
        bool(sequence),
    )


POSE_MAX_DT = 0.05  # s: a frame whose nearest motion-capture pose is farther in time has no pose


def _read_rows(path: Path, width: int, what: str) -> list[list[str]]:
    """Whitespace-separated rows of a TUM text file (lines starting with # are comments)."""
    if not path.is_file():
        raise DatasetError(f'{what} not found: {path}')
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        parts = line.split()
        if not parts or parts[0].startswith('#'):
            continue
        if len(parts) < width:
            raise DatasetError(f'{path}:{n}: expected {width} columns ({what}), got {line!r}')
        rows.append(parts[:width])
    if not rows:
        raise DatasetError(f'{path} holds no {what} rows')
    return rows


def poses(
    root,
    max_deg: float = 15.0,
    max_m: float = 0.3,
    min_gap_s: float = 2.0,
    step: int = 1,
    name: str | None = None,
    sequence: bool = True,
) -> Dataset:
    """A sequence with camera poses (the TUM RGB-D layout): DIR/rgb.txt (`timestamp file`),
    DIR/groundtruth.txt (`timestamp tx ty tz qx qy qz qw`, metres, any rate). Each frame takes the
    pose nearest in time (frames with none within POSE_MAX_DT are dropped, counted in info). Frame
    c is the same place as frame r when their relative rotation is at most max_deg degrees and their
    camera centres at most max_m metres apart. Every frame is a query and a reference (the loop
    protocol): query r may be answered only with frames at least min_gap_s seconds older, so the
    frames just before it, which see the same thing because no time has passed, are excluded.
    step > 1 keeps every step-th frame (a 30 Hz camera repeats itself; 3 gives 10 Hz)."""
    root = Path(root)
    if not (max_deg > 0 and max_m > 0 and min_gap_s >= 0 and step >= 1 and float(step).is_integer()):
        raise DatasetError(
            f'poses: need MAX_DEG > 0, MAX_M > 0, MIN_GAP_S >= 0 and a whole STEP >= 1, got '
            f'{max_deg}, {max_m}, {min_gap_s}, {step}'
        )
    try:
        frames = [(float(t), root / f) for t, f in _read_rows(root / 'rgb.txt', 2, 'timestamp file')]
        gt = np.array(
            [[float(v) for v in r] for r in _read_rows(root / 'groundtruth.txt', 8, 'timestamp tx ty tz qx qy qz qw')]
        )
    except ValueError as e:
        raise DatasetError(f'{root}: non-numeric timestamp or pose: {e}') from e
    frames.sort(key=lambda f: f[0])
    gt = gt[np.argsort(gt[:, 0], kind='stable')]
    t = np.array([f[0] for f in frames])
    right = np.clip(np.searchsorted(gt[:, 0], t), 0, len(gt) - 1)  # nearest pose: one of two neighbours
    left = np.maximum(right - 1, 0)
    j = np.where(np.abs(gt[left, 0] - t) <= np.abs(gt[right, 0] - t), left, right)
    has_pose = np.abs(gt[j, 0] - t) <= POSE_MAX_DT
    keep = has_pose & (np.arange(len(t)) % int(step) == 0)
    if not has_pose.any():
        raise DatasetError(
            f'{root}: no frame has a pose within {POSE_MAX_DT} s (do rgb.txt and groundtruth.txt use the same clock?)'
        )
    paths = [f[1] for f, k in zip(frames, keep) if k]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise DatasetError(f'{len(missing)} frames listed in {root / "rgb.txt"} are missing, e.g. {missing[0]}')
    t, pose = t[keep], gt[j[keep], 1:]
    quat = pose[:, 3:] / np.maximum(np.linalg.norm(pose[:, 3:], axis=1, keepdims=True), 1e-12)
    # relative rotation angle between unit quaternions: 2 acos |<q1, q2>|
    angle = np.degrees(2 * np.arccos(np.clip(np.abs(quat @ quat.T), 0, 1)))
    dist = np.linalg.norm(pose[:, None, :3] - pose[None, :, :3], axis=2)
    candidates = (t[:, None] - t[None, :] >= float(min_gap_s)) & ~np.eye(len(t), dtype=bool)
    stats = read_checked(paths)
    return Dataset(
        name or root.name,
        paths,
        paths,
        (angle <= max_deg) & (dist <= max_m) & candidates,
        candidates,
        {
            'max_deg': float(max_deg),
            'max_m': float(max_m),
            'min_gap_s': float(min_gap_s),
            'frames_without_pose': int((~has_pose).sum()),
            'step': int(step),
            'ref_sizes': [s[:2] for s in stats],
            'query_sizes': [s[:2] for s in stats],
        },
        bool(sequence),
    )


def gardenspoint(
    root, ref: str = 'day_right', query: str = 'night_right', tol: int = 2, drop='none', sequence: bool = True
) -> Dataset:
    """The public Gardens Point Walking archive (day_left/, day_right/, night_right/) as an aligned pair."""
    root = Path(root)
    for sub in (ref, query):
        if not (root / sub).is_dir():
            raise DatasetError(f'{root} is not the Gardens Point Walking layout: {sub}/ is missing')
    return aligned(root / ref, root / query, tol, name=f'gardenspoint-{ref}-vs-{query}', drop=drop, sequence=sequence)


SPEC_OPTIONS = {
    'aligned': ('drop', 'sequence'),
    'gardenspoint': ('drop', 'sequence'),
    'vprbench': ('sequence',),
    'loop': ('sequence',),
    'poses': ('sequence',),
}


def _options(spec: str, kind: str, parts: list[str]) -> tuple[list[str], dict]:
    """Positional parts and KEY=VALUE options (module doc) of a spec, options checked for `kind`."""
    args = [a for a in parts if '=' not in a]
    opts = {}
    for item in (a for a in parts if '=' in a):
        key, _, value = item.partition('=')
        key, value = key.strip(), value.strip()
        allowed = SPEC_OPTIONS.get(kind, ())
        if key not in allowed:
            raise DatasetError(f'{spec!r}: unknown option {key!r} for {kind} (options: {", ".join(allowed) or "none"})')
        if key == 'sequence':
            if value not in ('0', '1'):
                raise DatasetError(f'{spec!r}: sequence= takes 0 or 1, got {value!r}')
            opts['sequence'] = value == '1'
        else:
            opts['drop'] = parse_drop(value)
    return args, opts


def parse_spec(spec: str, frac=None) -> Dataset:
    """A dataset from a command-line SPEC: vprbench:DIR | aligned:DIR_REF,DIR_QUERY[,TOL] |
    loop:DIR,GT_FILE | gardenspoint:DIR[,REF,QUERY] | poses:DIR[,MAX_DEG,MAX_M,MIN_GAP_S[,STEP]] (TUM RGB-D
    layout, defaults 15 deg, 0.3 m, 2 s, every frame), each optionally followed by KEY=VALUE options
    (module doc: sequence=0|1; drop=... for aligned and gardenspoint). frac (start, end) applies to
    aligned data."""
    kind, _, rest = spec.partition(':')
    args, opts = _options(spec, kind, [a for a in rest.split(',') if a] if rest else [])
    if kind == 'aligned' and len(args) == 3 and not args[2].strip().isdigit():
        raise DatasetError(f'{spec!r}: the tolerance TOL must be a whole number of frames, got {args[2]!r}')
    if kind == 'aligned' and len(args) in (2, 3):
        return aligned(args[0], args[1], int(args[2]) if len(args) == 3 else 2, frac, **opts)
    if frac is not None and kind != 'aligned':
        raise DatasetError(f'--range applies to aligned datasets only, not {kind!r}')
    if kind == 'vprbench' and len(args) == 1:
        return vprbench(args[0], **opts)
    if kind == 'loop' and len(args) == 2:
        return loop(args[0], args[1], **opts)
    if kind == 'gardenspoint' and len(args) in (1, 3):
        return gardenspoint(*args, **opts)
    if kind == 'poses' and 1 <= len(args) <= 5:
        try:
            tolerances = [float(a) for a in args[1:]]
        except ValueError:
            raise DatasetError(f'{spec!r}: MAX_DEG, MAX_M, MIN_GAP_S and STEP must be numbers') from None
        return poses(args[0], *tolerances, **opts)
    raise DatasetError(
        f'cannot parse dataset {spec!r}; use vprbench:DIR, aligned:DIR_REF,DIR_QUERY[,TOL], '
        'loop:DIR,GT_FILE, gardenspoint:DIR[,REF,QUERY] or poses:DIR[,MAX_DEG,MAX_M,MIN_GAP_S[,STEP]], '
        'optionally followed by ,sequence=0|1 (and ,drop=MODES for aligned)'
    )
