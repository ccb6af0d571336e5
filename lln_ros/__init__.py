"""lln_ros: visual place recognition with discriminative landmarks (Xin et al., ICRA 2019).

The algorithm is importable without rclpy:

    from lln_ros import Extractor, LandmarkDatabase, MapStore, match_pair, load_image

Names are imported on first use, so `import lln_ros.mapstore` (the map server) does not pay for
torch, which only the extractor needs.
"""

from importlib import import_module

from .errors import DatasetError, DescriptorError, ImageError, LLNError, MapError, MessageError, ModelError

__version__ = '0.1.0'

_LAZY = {
    'Extractor': 'core.extractor',
    'load_image': 'io.image',
    'LandmarkSet': 'core.landmarks',
    'LandmarkBatch': 'core.landmarks',
    'select_landmarks': 'core.landmarks',
    'stack_landmarks': 'core.landmarks',
    'Candidate': 'core.retrieval',
    'LandmarkDatabase': 'core.retrieval',
    'MatchResult': 'core.similarity',
    'match_batch': 'core.similarity',
    'match_pair': 'core.similarity',
    'MapStore': 'mapstore',
    'MapCandidate': 'mapstore',
}
__all__ = [
    *_LAZY,
    'LLNError',
    'ImageError',
    'ModelError',
    'DescriptorError',
    'MapError',
    'MessageError',
    'DatasetError',
]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(f'.{_LAZY[name]}', __name__), name)
    raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
