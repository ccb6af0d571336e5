"""Exceptions with messages a user can act on. Every bad input ends in one of these, never in a
shape error from deep inside torch or numpy."""


class LLNError(ValueError):
    """Base class: bad input to lln_ros."""


class ImageError(LLNError):
    """An image that cannot be used: empty, wrong dtype or channels, unreadable file."""


class ModelError(LLNError):
    """A model or checkpoint that cannot be built or does not fit the configuration."""


class DescriptorError(LLNError):
    """Descriptors that cannot be compared: wrong size, non-finite, from another model."""


class MapError(LLNError):
    """A map file that cannot be opened or used: corrupt, truncated, from another model."""


class MessageError(LLNError):
    """A ROS message that cannot be decoded: missing fields, wrong sizes, truncated data."""


class DatasetError(LLNError):
    """A dataset that cannot be read: missing folders, unequal lengths, bad ground truth."""


class CameraError(LLNError):
    """Camera intrinsics or depth that cannot be used: uncalibrated (zeros), NaN, a size or encoding
    that does not match the image."""


class PoseError(LLNError):
    """A pose that cannot be stored or used: NaN, infinity, a quaternion that is not unit-norm."""
