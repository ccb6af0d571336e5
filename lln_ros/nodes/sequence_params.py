"""The matcher's parameters of the sequence search, with descriptors; defaults from the ROS-free
lln_ros.core.localizer.default_conf (one source). All are the Localizer's own (LOCALIZER_KEYS)."""

from __future__ import annotations

from ..core.localizer import CHOICES
from ..core.localizer import default_conf as LOC
from .parameters import Param

PARAMETERS = {
    'sequence_prefilter_k': Param(
        LOC['sequence_prefilter_k'],
        'with sequence_length > 0: first-stage candidates reranked, at least prefilter_k (the '
        'sequence search needs a score wherever the route may be); 0 = every keyframe',
        dynamic=True,
        range=(0, 1_000_000),
    ),
    'sequence_acquire_k': Param(
        LOC['sequence_acquire_k'],
        'with sequence_length > 0: first-stage candidates reranked while the window fills (its first '
        'sequence_length - 1 queries after a start or a new sequence), at least sequence_prefilter_k; 0 = off',
        dynamic=True,
        range=(0, 1_000_000),
    ),
    'sequence_length': Param(
        LOC['sequence_length'],
        'queries in the sequence search (0 = off, single-frame ranking); a change starts a new sequence',
        dynamic=True,
        range=(0, 10_000),
    ),
    'sequence_max_gap': Param(
        LOC['sequence_max_gap'],
        'seconds between query stamps beyond which a new sequence starts',
        dynamic=True,
        range=(1e-3, 1e6),
    ),
    'sequence_carry': Param(
        LOC['sequence_carry'],
        "with sequence_length > 0: the best N sequence ends' next places are scored beside the first "
        "stage's candidates, so a route the first stage loses stays scored; 0 = off",
        dynamic=True,
        range=(0, 10_000),
    ),
    'sequence_score_norm': Param(
        LOC['sequence_score_norm'],
        "each query's S in the line search: none (raw S) or zscore (standard deviations above its lowest "
        'candidate, so sequence_score compares across queries); a change starts a new sequence',
        dynamic=True,
        choices=CHOICES['sequence_score_norm'],
    ),
}
KEYS = tuple(PARAMETERS)
