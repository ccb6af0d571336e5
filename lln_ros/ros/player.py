"""Playing an MCAP bag (lln_ros.ros.bag) into ROS, as `ros2 bag play` would, without rosbag2:

play_bag(bag, rate=1.0, wait_subscribers=1)           # publish at the recorded timing
play_bag(bag, rate=4.0, clock_hz=40.0)                # ... and the bag time on /clock (sim time)
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable

from ..ros.bag import BagError, bag_info, message_class, read_raw


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

    def hold(self, bag_ns: int, seconds: float) -> None:
        """Publish `bag_ns` every period for `seconds` (the bag's start time while playback waits)."""
        end = time.monotonic() + seconds
        while True:
            self.publish(bag_ns)
            left = end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(self.period, left))

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
    bag's stamps as "now" (so max_query_age works on a replay, at any --rate). While playback
    waits (wait_subscribers, start_delay), /clock holds the bag's start time.
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
        # while playback waits, /clock already stands at the bag's start: a sim-time node has the
        # bag's clock before the first message (else it would judge that message by time 0)
        wait = clock.hold if clock is not None else (lambda _ns, seconds: time.sleep(seconds))
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
                wait(info['start_ns'], 0.02)
            log(f'subscribers ready: {counts}')
        if pace is not None:
            pace.start()
        if start_delay > 0:
            wait(info['start_ns'], start_delay)
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
            else:
                # one reading of the clock: checking `due > now` and sleeping `due - now'` with a
                # later now' raised 'sleep length must be non-negative' under load (CI, test_e2e_rgbd)
                time.sleep(max(0.0, due - time.monotonic()))
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
