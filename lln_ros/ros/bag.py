"""MCAP bags without rosbag2: write image sequences, read messages back (playing them into ROS is
lln_ros.ros.player).

    write_image_bag(paths, out, topic='/camera/image_raw', rate=10.0, compressed=False)
    write_bag(out, [(topic, msg, stamp_ns), ...])        # any rclpy message objects
    for topic, msg, t in read_messages(bag): ...         # deserialised rclpy messages
    bag_info(bag)                                         # topics, types, counts, duration

Bags are rosbag2 directories (metadata.yaml + one .mcap file, storage version 9) written with
`rosbags`; messages are serialised by rclpy itself (CDR), with the message definitions of the ROS 2
Jazzy typestore in the MCAP schemas, so `ros2 bag` and the `mcap` tools read them as usual.
"""

from __future__ import annotations

import importlib
import os
import shutil
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

import cv2

from ..errors import DatasetError, ImageError, LLNError
from ..io.datasets import list_images
from .msgs import array_to_compressed, array_to_image, make_header

DEFAULT_START_NS = 1_700_000_000 * 1_000_000_000  # 2023-11-14T22:13:20Z: bags are reproducible
DEFAULT_TOPIC = '/camera/image_raw'


class BagError(DatasetError):
    """A bag that cannot be written, opened or played, or an image folder that cannot become one."""


# --------------------------------------------------------------------------------------------
# image folders


def frame_images(folder: str | os.PathLike, pattern: str | None = None) -> tuple[list[Path], dict]:
    """The frames of an image folder, in natural order, and what was left out: (paths, skipped).

    Files that are not images (by suffix, datasets.IMAGE_SUFFIXES) are skipped. Without `pattern`,
    when the images are of several kinds, the frames are the most common suffix and the others are
    skipped too: rtabmap_loop/ holds samples_GT.bmp (its ground truth) beside 1.jpg ... With
    `pattern` (a glob) every matching image is a frame. skipped: {'not_image': [names],
    'other_kind': [names], 'kind': the frames' suffix or None}. DatasetError when nothing is left."""
    from collections import Counter

    from ..io.datasets import IMAGE_SUFFIXES, natural_key

    paths = list_images(folder, pattern)  # DatasetError: missing folder, no image at all
    files = Path(folder).glob(pattern) if pattern else Path(folder).iterdir()
    not_image = [f.name for f in files if f.is_file() and f.suffix.lower() not in IMAGE_SUFFIXES]
    not_image.sort(key=natural_key)
    kinds = Counter(p.suffix.lower() for p in paths)
    kind, other = None, []
    if not pattern and len(kinds) > 1:
        kind = kinds.most_common(1)[0][0]
        other = [p.name for p in paths if p.suffix.lower() != kind]
        paths = [p for p in paths if p.suffix.lower() == kind]
    return paths, {'not_image': not_image, 'other_kind': other, 'kind': kind}


def read_image_bgr(path: str | os.PathLike):
    """BGR uint8 (H, W, 3) of an image file; ImageError when it cannot be decoded."""
    if Path(path).is_dir():
        raise ImageError(f'{path} is a directory, not an image file')
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None or image.size == 0:
        raise ImageError(f'cannot decode image {path}')
    return image


# --------------------------------------------------------------------------------------------
# writing


def msgtype_of(msg) -> str:
    """'sensor_msgs/msg/Image' for a sensor_msgs.msg.Image instance (or class)."""
    cls = msg if isinstance(msg, type) else type(msg)
    package, kind = cls.__module__.split('.')[:2]
    return f'{package}/{kind}/{cls.__name__}'


def message_class(msgtype: str):
    """The rclpy message class of a type name ('sensor_msgs/msg/Image' or 'sensor_msgs/Image')."""
    parts = msgtype.split('/')
    if len(parts) == 2:
        parts = [parts[0], 'msg', parts[1]]
    if len(parts) != 3 or not all(parts):
        raise BagError(f'cannot parse message type {msgtype!r}')
    try:
        return getattr(importlib.import_module(f'{parts[0]}.{parts[1]}'), parts[2])
    except (ImportError, AttributeError) as exc:
        raise BagError(f'message type {msgtype} is not available in this Python environment ({exc})') from exc


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def write_bag(out: str | os.PathLike, records: Iterable[tuple], typestore=None) -> int:
    """Write (topic, rclpy message, stamp_ns) records to a new MCAP bag directory `out`.

    Message types are taken from the messages; their definitions from the ROS 2 Jazzy typestore.
    `out` must not exist. On any error the partial bag is removed. Returns the message count.
    """
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.rosbag2.errors import WriterError

    out = Path(out)
    if out.exists():
        raise BagError(f'{out} already exists; choose a new bag path')
    if not out.parent.exists():
        raise BagError(f'folder {out.parent} does not exist')
    typestore = typestore or _typestore()
    count = 0
    try:
        with Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
            connections = {}
            for topic, msg, stamp_ns in records:
                msgtype = msgtype_of(msg)
                conn = connections.get(topic)
                if conn is None:
                    if msgtype not in typestore.types:
                        raise BagError(f'message type {msgtype} is not in the ROS 2 Jazzy typestore')
                    conn = connections[topic] = writer.add_connection(topic, msgtype, typestore=typestore)
                elif conn.msgtype != msgtype:
                    raise BagError(f'topic {topic} carries {conn.msgtype}, got a {msgtype}')
                writer.write(conn, int(stamp_ns), serialize_message(msg))
                count += 1
    except BaseException as exc:
        shutil.rmtree(out, ignore_errors=True)
        if isinstance(exc, (WriterError, OSError)):
            raise BagError(f'cannot write bag {out}: {exc}') from exc
        raise
    return count


def frame_stamps(count: int, rate: float, start_ns: int = DEFAULT_START_NS) -> list[int]:
    """Nanosecond stamps of `count` frames at `rate` Hz from start_ns (rounded, no drift)."""
    if not rate > 0:
        raise BagError(f'rate must be positive, got {rate}')
    return [int(start_ns) + int(round(i * 1e9 / rate)) for i in range(count)]


def write_image_bag(
    paths: Sequence[str | os.PathLike],
    out: str | os.PathLike,
    topic: str = DEFAULT_TOPIC,
    rate: float = 10.0,
    compressed: bool = False,
    frame_id: str = 'camera',
    start_ns: int = DEFAULT_START_NS,
    jpeg_quality: int = 95,
) -> list[int]:
    """Write image files, in the given order, as one topic of a new MCAP bag at `rate` Hz.

    Messages are sensor_msgs/Image rgb8 or, with compressed=True, sensor_msgs/CompressedImage
    jpeg (re-encoded at jpeg_quality). Header stamps equal the bag timestamps. Returns the stamps.
    Raises BagError (no images, bad rate, existing output) or ImageError (undecodable image).
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise BagError('no images to write')
    stamps = frame_stamps(len(paths), rate, start_ns)

    def records():
        for path, stamp in zip(paths, stamps):
            bgr = read_image_bgr(path)
            header = make_header(stamp, frame_id)
            if compressed:
                msg = array_to_compressed(bgr, header, 'jpeg', 'bgr', jpeg_quality)
            else:
                msg = array_to_image(bgr[:, :, ::-1], 'rgb8', header)
            yield topic, msg, stamp

    write_bag(out, records())
    return stamps


def folder_to_bag(folder: str | os.PathLike, out: str | os.PathLike, **kwargs) -> list[int]:
    """write_image_bag over list_images(folder)."""
    return write_image_bag(list_images(folder), out, **kwargs)


# --------------------------------------------------------------------------------------------
# reading


def open_reader(path: str | os.PathLike):
    """An opened rosbags Reader (bag directory or a single .mcap file). Raises BagError."""
    from rosbags.rosbag2 import Reader

    path = Path(path)
    if not path.exists():
        raise BagError(f'bag {path} does not exist')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as exc:  # rosbags raises ReaderError, OSError, yaml and struct errors
        raise BagError(f'cannot open bag {path}: {exc}') from exc
    return reader


def read_raw(path: str | os.PathLike, topics: Iterable[str] | None = None) -> Iterator[tuple]:
    """(topic, msgtype, timestamp_ns, cdr bytes) of a bag's messages in time order."""
    reader = open_reader(path)
    try:
        conns = reader.connections
        if topics is not None:
            topics = set(topics)
            conns = [c for c in conns if c.topic in topics]
            if not conns:
                return
        try:
            for conn, stamp, raw in reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, stamp, raw
        except LLNError:
            raise
        except Exception as exc:
            raise BagError(f'bag {path} is corrupt: {exc}') from exc
    finally:
        reader.close()


def read_messages(path: str | os.PathLike, topics: Iterable[str] | None = None) -> Iterator[tuple]:
    """(topic, rclpy message, timestamp_ns) of a bag's messages in time order."""
    from rclpy.serialization import deserialize_message

    classes = {}
    for topic, msgtype, stamp, raw in read_raw(path, topics):
        cls = classes.get(msgtype) or classes.setdefault(msgtype, message_class(msgtype))
        yield topic, deserialize_message(raw, cls), stamp


def bag_info(path: str | os.PathLike) -> dict:
    """{'path', 'storage', 'message_count', 'start_ns', 'end_ns', 'duration_s', 'topics':
    {topic: {'type', 'count'}}} from the bag's index (no message is read)."""
    reader = open_reader(path)
    try:
        topics = {
            name: {'type': info.msgtype, 'count': int(info.msgcount)} for name, info in sorted(reader.topics.items())
        }
        count = int(reader.message_count)
        start = int(reader.start_time) if count else 0
        end = int(reader.end_time) if count else 0
        # rosbags' end_time is one past the last stamp
        duration = max(0, end - 1 - start) if count else 0
    except Exception as exc:
        raise BagError(f'cannot read bag {path}: {exc}') from exc
    finally:
        reader.close()
    return {
        'path': str(path),
        'storage': _storage_of(Path(path)),
        'message_count': count,
        'start_ns': start,
        'end_ns': start + duration,
        'duration_s': duration / 1e9,
        'topics': topics,
    }


def _storage_of(path: Path) -> str:
    files = [path] if path.is_file() else list(path.iterdir())
    suffixes = {f.suffix for f in files}
    return 'mcap' if '.mcap' in suffixes else 'sqlite3' if '.db3' in suffixes else 'unknown'


def _seconds(ns: int) -> str:
    return f'{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}'


def format_info(info: dict) -> str:
    """The text `lln-bag info` prints."""
    lines = [
        f'bag:       {info["path"]}',
        f'storage:   {info["storage"]}',
        f'messages:  {info["message_count"]}',
        f'duration:  {info["duration_s"]:.3f} s',
        f'start:     {_seconds(info["start_ns"])}',
        f'end:       {_seconds(info["end_ns"])}',
        f'topics:    {len(info["topics"])}',
    ]
    width = max((len(t) for t in info['topics']), default=0)
    for topic, t in info['topics'].items():
        lines.append(f'  {topic:<{width}}  {t["type"]:<30}  {t["count"]} msgs')
    return '\n'.join(lines)
