"""sensor_msgs/Image and sensor_msgs/CompressedImage <-> uint8 arrays (see the package docstring)."""

from __future__ import annotations

import array as _array
import struct

import cv2
import numpy as np
from sensor_msgs.msg import CompressedImage, Image
from std_msgs.msg import Header

from ...core.limits import check_pixels
from ...errors import MessageError

__all__ = [
    'IMAGE_ENCODINGS',
    'image_to_array',
    'compressed_size',
    'compressed_to_array',
    'array_to_image',
    'array_to_compressed',
    'message_to_array',
]

IMAGE_ENCODINGS = {  # encoding -> (channels, channel order)
    'rgb8': (3, 'rgb'),
    'bgr8': (3, 'bgr'),
    'mono8': (1, 'rgb'),
    'rgba8': (4, 'rgb'),
    'bgra8': (4, 'bgr'),
}


def image_to_array(msg: Image, max_pixels: int | None = None) -> tuple[np.ndarray, str]:
    """uint8 array and its channel order ('rgb' or 'bgr') from a sensor_msgs/Image.

    rgb8/bgr8 -> (H, W, 3), rgba8/bgra8 -> (H, W, 4), mono8 -> (H, W) ('rgb' by convention).
    Row padding (step > width * channels) is dropped. The result owns its memory.
    max_pixels: LimitError for a larger width x height, before anything is copied.
    """
    what = 'image'
    if not isinstance(msg, Image):
        raise MessageError(f'{what}: expected a sensor_msgs/Image, got {type(msg).__name__}')
    enc = msg.encoding
    if enc not in IMAGE_ENCODINGS:
        raise MessageError(f'{what}: unsupported encoding {enc!r}; supported: {", ".join(IMAGE_ENCODINGS)}')
    channels, order = IMAGE_ENCODINGS[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    if h == 0 or w == 0:
        raise MessageError(f'{what}: empty image ({w}x{h})')
    if max_pixels is not None:
        check_pixels(w, h, {'max_image_pixels': max_pixels}, what)
    row_bytes = w * channels
    if step < row_bytes:
        raise MessageError(
            f'{what}: step {step} is smaller than width x channels = {w} x {channels} = {row_bytes} for {enc}'
        )
    nbytes = len(msg.data)
    if nbytes < step * h:
        raise MessageError(
            f'{what}: data is truncated: {nbytes} bytes, expected step x height = {step} x {h} = {step * h}'
        )
    raw = np.frombuffer(msg.data, np.uint8, count=step * h).reshape(h, step)[:, :row_bytes]
    shape = (h, w) if channels == 1 else (h, w, channels)
    return np.ascontiguousarray(raw).reshape(shape), order


def compressed_size(data) -> tuple[str, int, int]:
    """('png' | 'jpeg', width, height) read from the header of PNG or JPEG bytes, without decoding.

    PNG: the IHDR chunk, which must come first. JPEG: the first start-of-frame marker (SOF0-15),
    reached by walking the marker segments. Raises MessageError for other data and for headers
    that do not give a size (a JPEG whose height comes later in a DNL marker, truncated headers).
    Hand-written (40 lines) rather than PIL.Image.open: PIL applies its own process-wide
    decompression-bomb limits and warnings, and OpenCV has no header-only reader."""
    head = bytes(data[:33])
    if head[:8] == b'\x89PNG\r\n\x1a\n':
        if len(head) < 24 or head[12:16] != b'IHDR':
            raise MessageError('PNG without an IHDR header chunk')
        w, h = struct.unpack('>II', head[16:24])
        return 'png', int(w), int(h)
    if head[:2] != b'\xff\xd8':
        raise MessageError(f'neither PNG nor JPEG data (starts with {head[:8].hex()})')
    view, i, n = memoryview(data), 2, len(data)
    while i + 4 <= n:
        if view[i] != 0xFF:
            raise MessageError(f'JPEG marker expected at byte {i}')
        marker = view[i + 1]
        if marker == 0xFF:  # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:  # standalone markers
            i += 2
            continue
        if marker in (0xD9, 0xDA):
            break  # end of image / start of scan before any frame header
        length = (view[i + 2] << 8) | view[i + 3]
        if length < 2:
            raise MessageError(f'JPEG segment of length {length} at byte {i}')
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if i + 9 > n:
                break
            h, w = (view[i + 5] << 8) | view[i + 6], (view[i + 7] << 8) | view[i + 8]
            if h == 0 or w == 0:
                raise MessageError(f'JPEG frame header says {w}x{h}')
            return 'jpeg', int(w), int(h)
        i += 2 + length
    raise MessageError('JPEG without a frame header (SOF) giving its size')


def compressed_to_array(msg: CompressedImage, max_pixels: int | None = None) -> tuple[np.ndarray, str]:
    """BGR uint8 (H, W, 3) and 'bgr' from a sensor_msgs/CompressedImage (jpeg or png).

    max_pixels: the size in the PNG/JPEG header is checked first (compressed_size): a small file
    that would decode to more pixels is refused with LimitError before it is decoded.

    EXIF orientation is ignored (cv2.IMREAD_IGNORE_ORIENTATION), as image_transport's compressed
    decoder does: ROS cameras never rotate, a raw sensor_msgs/Image has no EXIF, and the same frame
    must give the same pixels (and the size compressed_size read) on either transport."""
    what = 'compressed image'
    if not isinstance(msg, CompressedImage):
        raise MessageError(f'{what}: expected a sensor_msgs/CompressedImage, got {type(msg).__name__}')
    fmt = msg.format.lower()
    if 'compresseddepth' in fmt:
        raise MessageError(f'{what}: format {msg.format!r} (depth) is not supported; use jpeg or png')
    if len(msg.data) == 0:
        raise MessageError(f'{what}: no data')
    if max_pixels is not None:
        try:
            kind, w, h = compressed_size(msg.data)
        except MessageError as e:
            raise MessageError(
                f'{what}: cannot decode {len(msg.data)} bytes of format {msg.format!r}: {e} '
                '(jpeg and png are supported)'
            ) from None
        check_pixels(w, h, {'max_image_pixels': max_pixels}, f'{what} ({kind} header)')
    try:
        image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
    except cv2.error as e:  # e.g. above OpenCV's own OPENCV_IO_MAX_IMAGE_PIXELS
        raise MessageError(
            f'{what}: cannot decode {len(msg.data)} bytes of format {msg.format!r}: {str(e).strip().splitlines()[-1]}'
        ) from None
    if image is None or image.size == 0:
        raise MessageError(
            f'{what}: cannot decode {len(msg.data)} bytes of format {msg.format!r} (jpeg and png are supported)'
        )
    if max_pixels is not None:
        check_pixels(image.shape[1], image.shape[0], {'max_image_pixels': max_pixels}, what)
    return image, 'bgr'


def array_to_image(image: np.ndarray, encoding: str = 'rgb8', header: Header | None = None) -> Image:
    """sensor_msgs/Image (no row padding) from a uint8 array whose layout fits `encoding`."""
    if encoding not in IMAGE_ENCODINGS:
        raise MessageError(f'unsupported encoding {encoding!r}; supported: {", ".join(IMAGE_ENCODINGS)}')
    image = np.asarray(image)
    channels = IMAGE_ENCODINGS[encoding][0]
    if image.ndim == 3 and channels == 1 and image.shape[2] == 1:
        image = image[:, :, 0]
    expected = 2 if channels == 1 else 3
    if image.dtype != np.uint8 or image.ndim != expected or (channels > 1 and image.shape[2] != channels):
        raise MessageError(
            f'{encoding} needs a uint8 array of shape (H, W{"" if channels == 1 else f", {channels}"}), '
            f'got {image.dtype} {image.shape}'
        )
    h, w = image.shape[:2]
    if h == 0 or w == 0:
        raise MessageError(f'empty image ({w}x{h})')
    msg = Image()
    msg.header = header if header is not None else Header()
    msg.height, msg.width, msg.encoding = h, w, encoding
    msg.is_bigendian = 0
    msg.step = w * channels
    msg.data = _array.array('B', np.ascontiguousarray(image).tobytes())
    return msg


def array_to_compressed(
    image: np.ndarray, header: Header | None = None, fmt: str = 'jpeg', channel_order: str = 'bgr', quality: int = 95
) -> CompressedImage:
    """sensor_msgs/CompressedImage (jpeg or png) from a uint8 (H, W) or (H, W, 3) array."""
    if fmt not in ('jpeg', 'png'):
        raise MessageError(f"compressed format must be 'jpeg' or 'png', got {fmt!r}")
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
        raise MessageError(f'need a uint8 (H, W) or (H, W, 3) array, got {image.dtype} {image.shape}')
    if image.ndim == 3 and channel_order == 'rgb':
        image = image[:, :, ::-1]
    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)] if fmt == 'jpeg' else []
    ok, buf = cv2.imencode('.jpg' if fmt == 'jpeg' else '.png', np.ascontiguousarray(image), params)
    if not ok:
        raise MessageError(f'cannot encode a {image.shape} image as {fmt}')
    msg = CompressedImage()
    msg.header = header if header is not None else Header()
    msg.format = fmt
    msg.data = _array.array('B', buf.tobytes())
    return msg


def message_to_array(msg, max_pixels: int | None = None) -> tuple[np.ndarray, str]:
    """image_to_array or compressed_to_array, whichever fits the message."""
    if isinstance(msg, CompressedImage):
        return compressed_to_array(msg, max_pixels)
    return image_to_array(msg, max_pixels)
