"""The probe: an in-process node (its own rclpy Context on the nodes' domain) that publishes, collects,
calls services and plays bags with back-pressure. lln-demo drives the nodes with it; the tests too.

    probe = Probe(domain)
    probe.watch = [matcher, extractor]            # supervisor.NodeProcess: a dead one fails any wait
    got = probe.collect(PointCloud2, '/lln/candidates', msgs.cloud_to_candidates)
    probe.collect_answers(); probe.collect_diagnostics()
    probe.spin_until(lambda: len(got) == 3, 30, 'three answers')
    probe.play_paced(bag, publisher, 'query', stamps, 120, '/lln_extractor_query', confirm)

Waiting raises ProbeTimeout (a TimeoutError) or NodeDied; both are SupervisorError.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from . import topics
from .supervisor import SupervisorError, run_to_end

BAG_TOPIC = '/camera/image_raw'
HANDSHAKE_TRIES = 5  # sends of a phase's first frame until it is seen downstream
HANDSHAKE_WAIT = 3.0  # seconds to wait for that, after the extractor published it
MAX_IN_FLIGHT = 10  # paced queries the matcher may have unanswered (its queue holds queue_depth 100)


class ProbeTimeout(SupervisorError, TimeoutError):
    """Waited longer than asked for."""


class NodeDied(SupervisorError):
    """A watched node exited while the probe waited."""


class Probe:
    """A node of our own in its own Context on `domain` (an int, or an env dict with ROS_DOMAIN_ID)."""

    def __init__(self, domain, name: str = 'lln_probe'):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self.rclpy = rclpy
        self.domain = int(domain['ROS_DOMAIN_ID']) if isinstance(domain, dict) else int(domain)
        self.context = rclpy.Context()
        # no signal handlers: Ctrl-C stays a KeyboardInterrupt of the caller, which stops its nodes
        rclpy.init(context=self.context, domain_id=self.domain, signal_handler_options=SignalHandlerOptions.NO)
        self.node = rclpy.create_node(name, context=self.context, start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.watch: list = []  # NodeProcess: checked while waiting
        self.landmarks = {'keyframes': {}, 'query': {}}  # stamp -> (centers (n, 2), cell (w, h))
        self.duplicates = {'keyframes': 0, 'query': 0, 'candidates': 0}
        self.candidates: dict = {}  # query stamp -> structured array
        self.matches: dict = {}  # query stamp -> structured array
        self.bad_messages: list[str] = []
        self.diag: dict = {}  # node name -> {key: value}
        self._clients: dict = {}
        self.readers: dict = {}  # topic -> the collect() subscription

    def close(self) -> None:
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        finally:
            self.rclpy.try_shutdown(context=self.context)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # ------------------------------------------------------------------------------- the domain

    def foreign_nodes(self, seconds: float) -> list[str]:
        """Nodes of other processes on this domain (another probe's too)."""
        self.spin_for(seconds)
        names = [f'{ns.rstrip("/")}/{n}' for n, ns in self.node.get_node_names_and_namespaces()]
        if self.node.get_fully_qualified_name() in names:
            names.remove(self.node.get_fully_qualified_name())
        return names

    # ------------------------------------------------------------------------------- spinning

    def check_nodes(self) -> None:
        for p in self.watch:
            if not p.alive():
                raise NodeDied(p.died())

    def spin_until(self, done, timeout: float, what: str = 'condition', progress=None) -> None:
        """Spin until done(); ProbeTimeout on timeout, NodeDied when a watched node dies. `progress()`
        returning a changing value restarts the timeout (a long run that keeps moving never times out)."""
        last = progress() if progress else None
        deadline = time.monotonic() + timeout
        next_check = 0.0
        while not done():
            now = time.monotonic()
            if now >= next_check:
                self.check_nodes()
                next_check = now + 0.5
                if progress is not None:
                    value = progress()
                    if value != last:
                        last, deadline = value, now + timeout
            if now > deadline:
                raise ProbeTimeout(f'timed out after {timeout:g} s waiting for {what}' + self._state() + self._tails())
            self.executor.spin_once(timeout_sec=0.02)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def wait_quietly(self, done, seconds: float) -> bool:
        """spin_until without the timeout error: whether done() came true in time."""
        try:
            self.spin_until(done, seconds, 'a confirmation')
            return True
        except ProbeTimeout:
            return False

    def wait_for_peers(self, publisher, topics: list[str] = (), timeout: float = 60.0) -> None:
        """Until `publisher` has a subscriber and every topic in `topics` has a publisher."""
        self.spin_until(
            lambda: (
                (publisher is None or publisher.get_subscription_count() > 0)
                and all(self.node.count_publishers(t) > 0 for t in topics)
            ),
            timeout,
            'peers',
        )

    def _state(self) -> str:
        if not (self.landmarks['keyframes'] or self.landmarks['query'] or self.candidates or self.diag):
            return ''
        seen = {k: len(v) for k, v in self.landmarks.items()}
        return (
            f'\n  seen so far: landmarks {seen}, answers {len(self.candidates)}; node counters '
            f'{json.dumps(self.diag, sort_keys=True)}'
        )

    def _tails(self) -> str:
        return ''.join(f'\n  the end of {p.log_path}:\n{p.tail(8)}' for p in self.watch)

    # ------------------------------------------------------------------------------- topics, services

    def publisher(self, msg_type, topic: str, depth: int = 100):
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        return self.node.create_publisher(
            msg_type, topic, QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
        )

    def collect(self, msg_type, topic: str, decode=lambda m: m, depth: int = 1000) -> list:
        """Everything that arrives on `topic` (reliable), decoded, in arrival order."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        got: list = []
        self.readers[topic] = self.node.create_subscription(
            msg_type,
            topic,
            lambda m: got.append(decode(m)),
            QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE),
        )
        return got

    def matched_writers(self, topic: str) -> int:
        """How many writers the collect() reader of `topic` has matched. A volatile reader gets
        nothing a writer sent before this match, though the writer may count the reader already."""
        return self.readers[topic].get_publisher_count()

    def call(self, srv_type, name: str, timeout: float = 30.0, request=None):
        """One service call: waits for the service, then for its answer."""
        client = self._clients.get((srv_type, name))
        if client is None:
            client = self._clients[(srv_type, name)] = self.node.create_client(srv_type, name)
        self.spin_until(client.service_is_ready, timeout, f'service {name}')
        future = client.call_async(request if request is not None else srv_type.Request())
        self.spin_until(future.done, timeout, f'an answer from {name}')
        return future.result()

    def matcher_info(self, timeout: float, service: str = '/lln_matcher/info') -> dict:
        """The matcher's ~/info (std_srvs/Trigger, JSON in its message)."""
        from std_srvs.srv import Trigger

        response = self.call(Trigger, service, timeout)
        if not response.success:
            raise SupervisorError(f'{service} failed: {response.message}')
        return json.loads(response.message)

    # ------------------------------------------------------------------------------- collecting answers

    def collect_answers(self) -> None:
        """Subscribe to /lln/keyframes, /lln/query (landmark clouds), /lln/candidates and /lln/matches (the
        root namespace, where lln-demo runs the nodes), keyed by stamp."""
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2

        reliable = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        for kind, topic in (('keyframes', topics.KEYFRAMES), ('query', topics.QUERY)):
            self.node.create_subscription(
                PointCloud2, '/' + topic, lambda m, k=kind: self._on_landmarks(k, m), reliable
            )
        self.node.create_subscription(PointCloud2, '/' + topics.CANDIDATES, self._on_candidates, reliable)
        self.node.create_subscription(PointCloud2, '/' + topics.MATCHES, self._on_matches, reliable)

    def collect_diagnostics(self) -> None:
        """The latest /diagnostics status of every node, in self.diag; read with counter()."""
        from diagnostic_msgs.msg import DiagnosticArray

        self.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 100)

    def _on_landmarks(self, kind: str, msg) -> None:
        from . import msgs

        stamp = msgs.stamp_to_ns(msg.header)
        try:
            rows = msgs.cloud_to_array(msg, msgs.LANDMARK_FIELDS[:4], f'{kind} cloud')
        except Exception as e:  # noqa: BLE001  one bad message is reported, never fatal here
            self.bad_messages.append(f'{kind} @ {stamp}: {e}')
            rows = None
        seen = self.landmarks[kind]
        if stamp in seen:
            self.duplicates[kind] += 1
            return
        if rows is None or len(rows) < 2:
            seen[stamp] = (None, None)
            return
        seen[stamp] = (
            np.stack([rows['u'][1:], rows['v'][1:]], axis=1).astype(np.float32),
            (float(rows['w'][1]), float(rows['h'][1])),
        )

    def _on_candidates(self, msg) -> None:
        from . import msgs

        stamp = msgs.stamp_to_ns(msg.header)
        if stamp in self.candidates:
            self.duplicates['candidates'] += 1
            return
        try:
            self.candidates[stamp] = msgs.cloud_to_candidates(msg)
        except Exception as e:  # noqa: BLE001
            self.bad_messages.append(f'candidates @ {stamp}: {e}')
            self.candidates[stamp] = None

    def _on_matches(self, msg) -> None:
        from . import msgs

        stamp = msgs.stamp_to_ns(msg.header)
        try:
            self.matches.setdefault(stamp, msgs.cloud_to_matches(msg))
        except Exception as e:  # noqa: BLE001
            self.bad_messages.append(f'matches @ {stamp}: {e}')

    def _on_diag(self, msg) -> None:
        for status in msg.status:
            self.diag[status.name] = {kv.key: kv.value for kv in status.values}

    def counter(self, node: str, key: str) -> int:
        try:
            return int(self.diag.get(node, {}).get(key, 0))
        except ValueError:
            return 0

    # ------------------------------------------------------------------------------- playing bags

    def image_publisher(self, topic: str):
        from sensor_msgs.msg import Image

        return self.publisher(Image, topic, depth=10)

    def play_paced(
        self,
        bag_path: Path,
        publisher,
        out_kind: str,
        stamps: list,
        timeout: float,
        extractor: str,
        confirm,
        bar=None,
        backlog=None,
    ) -> dict:
        """Publish the bag's frames (the recorded CDR bytes, as a bag player does), each once the
        extractor has published the previous frame's landmarks on `out_kind`: its one-frame mailbox
        never holds two frames, so none is dropped. backlog: a count of what the next node has not
        finished (unanswered queries); frames wait while it is MAX_IN_FLIGHT or more, so a matcher
        slower than the extractor (prefilter_k 0 on a large map) never overflows its queue.

        Frame 0 is a handshake: seeing every endpoint in the graph does not mean the extractor's
        writer has matched the matcher's reader yet (discovery is not symmetric in time), and a
        volatile sample published before that is lost for good. So once the extractor has published
        frame 0, `confirm(stamp)` checks that it arrived downstream (the map counts a keyframe / the
        query is answered); if not, frame 0 is sent again (HANDSHAKE_TRIES times at most). Returns
        timing and the number of frames sent again."""
        from ..ros import bag

        seen = self.landmarks[out_kind]
        self.spin_until(
            lambda: publisher.get_subscription_count() > 0, timeout, f'a subscriber on {publisher.topic_name}'
        )
        t0 = time.monotonic()
        waits, resent = [], 0
        for i, (_topic, _type, stamp, raw) in enumerate(bag.read_raw(bag_path, [BAG_TOPIC])):
            if stamp != stamps[i]:
                raise SupervisorError(f'{bag_path}: frame {i} has stamp {stamp}, expected {stamps[i]}')
            t = time.monotonic()
            if i == 0:
                for _attempt in range(HANDSHAKE_TRIES):
                    published = self.counter(extractor, 'published')
                    publisher.publish(bytes(raw))
                    self.spin_until(
                        lambda s=stamp, n=published: s in seen or self.counter(extractor, 'published') > n,
                        timeout,
                        f'the landmarks of the first frame of {bag_path.name} on /{out_kind}',
                    )
                    if confirm(stamp):
                        break
                    resent += 1
                else:
                    raise SupervisorError(
                        f'the first frame of {bag_path.name} never reached the matcher through '
                        f'/{out_kind} ({HANDSHAKE_TRIES} tries)' + self._state() + self._tails()
                    )
                # our own reader may match a little later than the matcher's
                self.wait_quietly(lambda s=stamp: s in seen, HANDSHAKE_WAIT)
            else:
                if backlog is not None:
                    self.spin_until(lambda: backlog() < MAX_IN_FLIGHT, timeout, f'the matcher to catch up ({i})')
                publisher.publish(bytes(raw))
                self.spin_until(
                    lambda s=stamp: s in seen, timeout, f'the landmarks of frame {i} of {bag_path.name} on /{out_kind}'
                )
            waits.append(time.monotonic() - t)
            if bar is not None:
                bar.update(1)
        total = time.monotonic() - t0
        return {
            'seconds': total,
            'frames': len(waits),
            'frames_per_s': len(waits) / total if total else None,
            'median_frame_ms': 1e3 * float(np.median(waits)) if waits else None,
            'resent': resent,
        }

    def play_fixed(
        self,
        player: list,
        bag_path: Path,
        topic: str,
        hz: float,
        out_kind: str,
        stamps: list,
        env: dict,
        cwd: Path,
        timeout: float,
        log_path: Path,
        bar=None,
    ) -> dict:
        """`lln-bag play BAG --topic-remap /camera/image_raw:=TOPIC` at the recorded rate (HZ) in its own
        process, as `ros2 bag play` would; then wait for the extractor to publish what it got."""
        seen = self.landmarks[out_kind]
        cmd = player + [
            'play',
            str(bag_path),
            '--rate',
            '1',
            '--topic-remap',
            f'{BAG_TOPIC}:={topic}',
            '--wait-subscribers',
            '1',
            '--wait-timeout',
            f'{timeout:g}',
        ]
        t0 = time.monotonic()
        shown = [0]

        def while_playing():
            self.check_nodes()
            self.spin_for(0.1)
            if bar is not None and len(seen) > shown[0]:
                bar.update(len(seen) - shown[0])
                shown[0] = len(seen)

        status = run_to_end(cmd, env, cwd, log_path, while_playing)
        if status != 0:
            played = Path(log_path).read_text(errors='replace')
            raise SupervisorError(f'lln-bag play {bag_path.name} failed (status {status}):\n{played[-2000:]}')
        # the extractor may still be working on its last frame; stop when every frame is in or nothing moves
        wanted = set(stamps)
        try:
            self.spin_until(
                lambda: wanted <= set(seen), min(timeout, 15.0), 'the last landmarks', progress=lambda: len(seen)
            )
        except ProbeTimeout:
            pass  # frames the extractor dropped never come: counted by the caller
        if bar is not None:
            bar.update(len(seen) - bar.n)
        total = time.monotonic() - t0
        return {
            'seconds': total,
            'frames': len(stamps),
            'frames_per_s': len(stamps) / total if total else None,
            'rate_hz': hz,
        }


def free_domain_probe(requested: int | None = None, name: str = 'lln_probe', tries: int = 8) -> Probe:
    """A Probe on a domain where no other node runs on this host (or on `requested`)."""
    import os

    if requested is not None:
        return Probe(requested, name)
    start = (os.getpid() * 7919 + int(time.time())) % 100
    busy = []
    for step in range(tries):
        domain = 1 + (start + step * 37) % 100
        probe = Probe(domain, name)
        others = probe.foreign_nodes(1.0)
        if not others:
            return probe
        busy.append(f'{domain} ({len(others)} nodes)')
        probe.close()
    raise SupervisorError(f'no free ROS_DOMAIN_ID found (busy: {", ".join(busy)}); pass a domain id')
