"""lln_ros: visual place recognition with discriminative landmarks (Xin et al., ICRA 2019).

The algorithm is importable without rclpy:

    from lln_ros import Extractor, LandmarkDatabase, match_pair, load_image
"""
from .errors import DatasetError, DescriptorError, ImageError, LLNError, MapError, MessageError, ModelError
from .extractor import Extractor
from .image import load_image
from .landmarks import LandmarkBatch, LandmarkSet, select_landmarks, stack_landmarks
from .retrieval import Candidate, LandmarkDatabase
from .similarity import MatchResult, match_batch, match_pair

__version__ = '0.1.0'
__all__ = ['Extractor', 'LandmarkDatabase', 'Candidate', 'LandmarkSet', 'LandmarkBatch', 'MatchResult',
           'match_pair', 'match_batch', 'select_landmarks', 'stack_landmarks', 'load_image',
           'LLNError', 'ImageError', 'ModelError', 'DescriptorError', 'MapError', 'MessageError',
           'DatasetError']
