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
