"""MCAP bags without rosbag2: write image sequences, read messages back, play them into ROS.

Why this module is past 500 lines: writing, reading, describing and playing bags (with /clock and
pacing) share the message-type and QoS code; split, each part would import the others.

    write_image_bag(paths, out, topic='/camera/image_raw', rate=10.0, compressed=False)
    write_bag(out, [(topic, msg, stamp_ns), ...])        # any rclpy message objects
    for topic, msg, t in read_messages(bag): ...         # deserialised rclpy messages
    bag_info(bag)                                         # topics, types, counts, duration
    play_bag(bag, rate=1.0, wait_subscribers=1)           # publish at the recorded timing
    play_bag(bag, rate=4.0, clock_hz=40.0)                # ... and the bag time on /clock (sim time)

Bags are rosbag2 directories (metadata.yaml + one .mcap file, storage version 9) written with
`rosbags`; messages are serialised by rclpy itself (CDR), with the message definitions of the ROS 2
Jazzy typestore in the MCAP schemas, so `ros2 bag` and the `mcap` tools read them as usual.
"""

from __future__ import annotations

import importlib
import os
import shutil
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import cv2

from ..errors import DatasetError, ImageError, LLNError
from ..msgs import array_to_compressed, array_to_image, make_header
from .datasets import list_images

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

    from .datasets import IMAGE_SUFFIXES, natural_key

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


# --------------------------------------------------------------------------------------------
# playing


def parse_remaps(items: Iterable[str]) -> dict[str, str]:
    """['A:=B', ...] -> {'A': 'B'}."""
    remaps = {}
    for item in items or ():
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst:
            raise BagError(f'topic remap {item!r} must look like /from:=/to')
        remaps[src] = dst
    return remaps


def make_qos(reliability: str = 'reliable', depth: int = 100):
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

    policies = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}
    if reliability not in policies:
        raise BagError(f"qos must be 'reliable' or 'best_effort', got {reliability!r}")
    if depth < 1:
        raise BagError(f'qos depth must be at least 1, got {depth}')
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=int(depth),
        reliability=policies[reliability],
        durability=DurabilityPolicy.VOLATILE,
    )


class SubscriberTimeout(BagError):
    """Not enough subscribers appeared before the wait timeout."""


CLOCK_TOPIC = '/clock'


class BagClock:
    """Bag time as a function of wall time during playback: bag_ns(now) = t0_bag + (now - t0_wall) * rate.
    Published on /clock (rosgraph_msgs/Clock), so nodes with use_sim_time=true run on the bag's time,
    at any playback rate. QoS as rosbag2's --clock (rclcpp::ClockQoS): best effort, keep last 1."""

    def __init__(self, node, rate: float, hz: float):
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock

        if not hz > 0:
            raise BagError(f'clock rate must be positive, got {hz}')
        self._msg = Clock()
        self.pub = node.create_publisher(
            Clock,
            CLOCK_TOPIC,
            QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT),
        )
        self.rate, self.period = rate, 1.0 / hz
        self.t0_wall = self.t0_bag = None
        self.last_ns = None

    def start(self, t0_wall: float, t0_bag: int) -> None:
        self.t0_wall, self.t0_bag = t0_wall, t0_bag
        self.publish(t0_bag)

    def now_ns(self, wall: float) -> int:
        return self.t0_bag + int(round((wall - self.t0_wall) * 1e9 * self.rate))

    def publish(self, bag_ns: int) -> None:
        if self.last_ns is not None and bag_ns < self.last_ns:
            return  # /clock never runs backwards (messages of one instant on several topics)
        self.last_ns = bag_ns
        self._msg.clock.sec, self._msg.clock.nanosec = divmod(int(bag_ns), 1_000_000_000)
        self.pub.publish(self._msg)

    def sleep_until(self, wall: float) -> None:
        """Sleep until `wall` (time.monotonic), publishing the bag time every period meanwhile."""
        while True:
            now = time.monotonic()
            if now >= wall:
                return
            time.sleep(min(self.period, wall - now))
            self.publish(self.now_ns(min(time.monotonic(), wall)))


class _Pace:
    """Counts the messages on a node's output topic (its type read from the graph) so that the
    player can wait for one output per published message."""

    def __init__(self, node, topic: str, timeout: float, log: Callable[[str], None]):
        if not timeout > 0:
            raise BagError(f'pace timeout must be positive, got {timeout}')
        from rclpy.executors import SingleThreadedExecutor

        self.node, self.topic, self.timeout, self.log = node, node.resolve_topic_name(topic), timeout, log
        self.seen, self.expected_offset, self.timeouts, self.sub = 0, 0, 0, None
        self.executor = SingleThreadedExecutor(context=node.context)
        self.executor.add_node(node)

    def _subscribe(self, deadline: float) -> bool:
        while self.sub is None:
            types = dict(self.node.get_topic_names_and_types()).get(self.topic)
            if types:
                self.sub = self.node.create_subscription(
                    message_class(types[0]), self.topic, self._on_msg, make_qos('reliable', 1000)
                )
                return True
            if time.monotonic() > deadline:
                return False
            self.executor.spin_once(timeout_sec=0.02)
        return True

    def start(self, settle: float = 0.5) -> None:
        """Subscribe before the first message goes out, and let the subscription match its publisher."""
        if self._subscribe(time.monotonic() + self.timeout):
            end = time.monotonic() + settle
            while time.monotonic() < end:
                self.executor.spin_once(timeout_sec=0.02)
            self.log(f'pacing on {self.topic}')
        else:
            self.log(f'pace: {self.topic} has no publisher yet; pacing starts when it appears')

    def _on_msg(self, _msg) -> None:
        self.seen += 1

    def wait(self, published: int) -> None:
        deadline = time.monotonic() + self.timeout
        if self._subscribe(deadline):
            while self.seen + self.expected_offset < published and time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.02)
        if self.seen + self.expected_offset < published:
            self.timeouts += 1
            self.expected_offset = published - self.seen  # go on from here, do not wait for it again
            if self.timeouts == 1 or self.timeouts % 100 == 0:
                self.log(
                    f'pace: no message on {self.topic} within {self.timeout:g} s of message {published} '
                    f'({self.timeouts} time(s)); going on'
                )


def play_bag(
    path: str | os.PathLike,
    rate: float = 1.0,
    remaps: dict[str, str] | None = None,
    qos: str = 'reliable',
    qos_depth: int = 100,
    wait_subscribers: int = 0,
    wait_timeout: float = 10.0,
    topics: Iterable[str] | None = None,
    start_delay: float = 0.0,
    linger: float = 0.5,
    log: Callable[[str], None] | None = None,
    context=None,
    clock_hz: float = 0.0,
    pace_topic: str = '',
    pace_timeout: float = 10.0,
    on_published: Callable[[int], None] | None = None,
) -> int:
    """Publish a bag's messages into the ROS graph at the recorded timing divided by `rate`.

    The recorded CDR bytes are published as they are (rclpy's publish of `bytes`), on publishers
    of the recorded types. remaps: {bag topic: published topic}. With wait_subscribers=N, playback
    starts only when every played topic has at least N subscribers (SubscriberTimeout after
    wait_timeout seconds). Reliable publishers wait (up to 5 s) for every message to be
    acknowledged before returning; best-effort ones linger `linger` seconds (without it the last
    sample is often lost when the writer is destroyed). Returns the number of messages published.
    Uses its own rclpy Context unless one is given, so it can run beside other nodes.
    clock_hz > 0: also publish the bag time on /clock (rosgraph_msgs/Clock) at clock_hz and with
    every message, as `ros2 bag play --clock` does; nodes run with use_sim_time:=true then see the
    bag's stamps as "now" (so max_query_age works on a replay, at any --rate).
    pace_topic: lossless replay into a node slower than the bag (an extractor keeps only the newest
    waiting frame, by design): after each message, wait until pace_topic (e.g. the extractor's
    `landmarks`) has carried as many messages as were published, up to pace_timeout seconds (then
    log it and go on). The recorded timing stays the fastest pace; a wait shifts the rest of the bag
    (and its /clock) later instead of bursting to catch up.
    on_published(count): called once every message is out (and acknowledged), before the DDS teardown;
    a command line arms a teardown watchdog there (Fast DDS can deadlock deleting a participant while
    a subscriber's participant goes away at the same instant).
    """
    import rclpy
    from rclpy.duration import Duration

    if not rate > 0:
        raise BagError(f'rate must be positive, got {rate}')
    remaps = dict(remaps or {})
    log = log or (lambda _msg: None)
    info = bag_info(path)
    wanted = set(info['topics']) if topics is None else set(topics)
    unknown = wanted - set(info['topics'])
    if unknown:
        raise BagError(f'topic(s) {sorted(unknown)} are not in the bag (it has {sorted(info["topics"])})')
    if not wanted:
        raise BagError(f'bag {path} has no topics to play')
    classes = {t: message_class(info['topics'][t]['type']) for t in sorted(wanted)}
    profile = make_qos(qos, qos_depth)

    own_context = context is None
    if own_context:
        from rclpy.signals import SignalHandlerOptions

        context = rclpy.Context()
        # no rclpy signal handlers: with them, Ctrl-C shuts the context down and the loop below
        # would race through the rest of the bag instead of stopping with KeyboardInterrupt
        rclpy.init(context=context, signal_handler_options=SignalHandlerOptions.NO)
    node = None
    count = 0
    try:
        node = rclpy.create_node('lln_bag_play', context=context, start_parameter_services=False)
        publishers = {t: node.create_publisher(cls, remaps.get(t, t), profile) for t, cls in classes.items()}
        clock = BagClock(node, rate, clock_hz) if clock_hz > 0 else None
        pace = _Pace(node, pace_topic, pace_timeout, log) if pace_topic else None
        if wait_subscribers > 0:
            deadline = time.monotonic() + wait_timeout
            while True:
                counts = {p.topic_name: p.get_subscription_count() for p in publishers.values()}
                if min(counts.values()) >= wait_subscribers:
                    break
                if time.monotonic() > deadline:
                    raise SubscriberTimeout(
                        f'timed out after {wait_timeout:g} s waiting for {wait_subscribers} '
                        f'subscriber(s) per topic; have {counts}'
                    )
                time.sleep(0.02)
            log(f'subscribers ready: {counts}')
        if pace is not None:
            pace.start()
        if start_delay > 0:
            time.sleep(start_delay)
        log(
            f'playing {info["message_count"]} messages on {len(publishers)} topic(s) at rate {rate:g}'
            + (f', bag time on {CLOCK_TOPIC} at {clock_hz:g} Hz' if clock is not None else '')
        )
        t0_wall, t0_bag = None, None
        for topic, _msgtype, stamp, raw in read_raw(path, wanted):
            if t0_wall is None:
                t0_wall, t0_bag = time.monotonic(), stamp
                if clock is not None:
                    clock.start(t0_wall, t0_bag)
            due = t0_wall + (stamp - t0_bag) / 1e9 / rate
            if clock is not None:
                clock.sleep_until(due)
                clock.publish(stamp)  # the clock reaches a message's stamp before the message goes out
            elif due > time.monotonic():
                time.sleep(due - time.monotonic())
            publishers[topic].publish(bytes(raw))
            count += 1
            if pace is not None:
                pace.wait(count)
                lag = time.monotonic() - due
                if lag > 0:  # the node was slower than the bag: the rest of the bag starts later
                    t0_wall += lag
                    if clock is not None:
                        clock.start(t0_wall, t0_bag)
        if profile.reliability == rclpy.qos.ReliabilityPolicy.RELIABLE:
            for pub in publishers.values():
                pub.wait_for_all_acked(Duration(seconds=5))
        elif linger > 0 and count:
            time.sleep(linger)  # best effort: destroying the writer at once can lose the last sample
        log(f'published {count} messages')
        if on_published is not None:
            on_published(count)
    finally:
        if node is not None:
            node.destroy_node()
        if own_context:
            context.try_shutdown()
    return count
