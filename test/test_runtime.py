"""Issue 16 node behaviour over real DDS, colcon-installed matcher in its own process:
- run-time parameters through rcl_interfaces/srv/SetParameters (a parameter client, as
  `ros2 param set` is): accepted ones take effect on the next query, invalid ones are refused with a
  reason (range, choices, type, read-only), descriptors say which is which;
- /diagnostics levels: WARN for stale queries, ERROR while a model mismatch refuses all input;
- sim time: an MCAP bag of real landmark clouds replayed by `lln-bag play --clock` at 4x into a
  matcher with use_sim_time and max_query_age: every query answered, stamps unchanged, ages small;
  the same replay without sim time drops every query and says why.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rcl_interfaces.msg import Parameter, ParameterType, ParameterValue
from rcl_interfaces.srv import DescribeParameters, SetParameters
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from lln_ros.ros import bag, msgs
from ros_harness import Probe, RosProcess, installed_env, ros_env

MATCHER = '/lln_matcher'
T0 = 1_700_000_000 * 10**9


@pytest.fixture(scope='module')
def places(extractor, photo):
    crops = [photo[y : y + 256, x : x + 224] for y in (0, 170, 340) for x in (0, 144, 288)]
    sets = extractor.extract_batch([np.ascontiguousarray(c) for c in crops])
    return {'sets': sets, 'model': extractor.model_info}


class Matcher:
    """The installed matcher + a probe with /diagnostics of it and a parameter client."""

    def __init__(self, install, tmp_path, places, *ros_args):
        self.env = installed_env(install, ros_env(tmp_path))
        self.proc = RosProcess(
            install / 'lln_ros' / 'lib' / 'lln_ros' / 'matcher',
            [
                '-p',
                f'map_path:={tmp_path / "map.db"}',
                '-p',
                'diagnostics_period:=0.2',
                '-p',
                f'descriptor_space:={places["model"]["descriptor_space"]}',
                *ros_args,
            ],
            self.env,
            tmp_path / 'matcher.log',
        )
        self.probe = Probe(self.env)
        self.status = None
        self.probe.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)
        self.probe.spin_until(lambda: self.status is not None or not self.proc.alive(), 120, 'matcher diagnostics')
        assert self.proc.alive(), self.proc.log()

    def _on_diag(self, msg):
        for s in msg.status:
            if s.name == MATCHER:
                self.status, self.diag_stamp = s, msgs.stamp_to_ns(msg.header.stamp)

    def values(self) -> dict:
        return {kv.key: kv.value for kv in self.status.values}

    def call(self, srv, name, request, timeout=30.0):
        client = self.probe.node.create_client(srv, f'{MATCHER}/{name}')
        self.probe.spin_until(client.service_is_ready, timeout, name)
        future = client.call_async(request)
        self.probe.spin_until(future.done, timeout, f'answer of {name}')
        return future.result()

    def info(self) -> dict:
        """The matcher's ~/info service answer (map, counters, matched readers and writers)."""
        return json.loads(self.probe.call(Trigger, f'{MATCHER}/info').message)  # the probe keeps the client

    def set(self, **values) -> list:
        """SetParameters with these values, one request; the list of SetParametersResult."""
        kinds = {
            bool: (ParameterType.PARAMETER_BOOL, 'bool_value'),
            int: (ParameterType.PARAMETER_INTEGER, 'integer_value'),
            float: (ParameterType.PARAMETER_DOUBLE, 'double_value'),
            str: (ParameterType.PARAMETER_STRING, 'string_value'),
        }
        params = []
        for name, v in values.items():
            kind, field = kinds[type(v)]
            params.append(Parameter(name=name, value=ParameterValue(type=kind, **{field: v})))
        return self.call(SetParameters, 'set_parameters', SetParameters.Request(parameters=params)).results

    def wait_status(self, check, what, timeout=30.0):
        self.probe.spin_until(lambda: self.status is not None and check(self.status), timeout, what)

    def close(self) -> int:
        self.probe.close()
        return self.proc.stop()


def test_runtime_parameters_and_diagnostic_levels(colcon_install, tmp_path, places):
    m = Matcher(colcon_install, tmp_path, places, '-p', 'mode:=localization')
    try:
        keyframes = m.probe.publisher(PointCloud2, 'lln/keyframes')
        queries = m.probe.publisher(PointCloud2, 'lln/query')
        answers = m.probe.collect(PointCloud2, 'lln/candidates', msgs.cloud_to_candidates)
        m.probe.spin_until(lambda: keyframes.get_subscription_count() and queries.get_subscription_count(), 60, 'subs')
        for i, lset in enumerate(places['sets']):
            keyframes.publish(msgs.landmarks_to_cloud(lset, msgs.make_header(T0 + i * 10**9)))
        m.wait_status(lambda s: m.values().get('keyframes') == str(len(places['sets'])), 'keyframes stored')
        assert m.status.level == DiagnosticStatus.OK and m.status.message == 'running'

        described = m.call(
            DescribeParameters,
            'describe_parameters',
            DescribeParameters.Request(names=['k', 'offset_scale', 'mode', 'method']),
        ).descriptors
        k, offset_scale, mode, method = described
        assert not k.read_only and (k.integer_range[0].from_value, k.integer_range[0].to_value) == (1, 10_000_000)
        assert not offset_scale.read_only and offset_scale.floating_point_range[0].from_value == 1e-3
        assert mode.read_only and 'read-only' in mode.additional_constraints
        assert 'one of: lln | holistic' in method.additional_constraints

        # accepted: takes effect on the next query
        assert [r.successful for r in m.set(k=2, min_score=0.5)] == [True, True]
        queries.publish(msgs.landmarks_to_cloud(places['sets'][4], msgs.make_header(T0 + 100 * 10**9)))
        m.probe.spin_until(lambda: answers, 30, 'an answer')
        assert len(answers[-1]) == 2 and answers[-1]['score'].min() >= 0.5
        # refused, with the reason, and nothing changes
        for values, reason in (
            ({'k': 0}, 'out of range'),
            ({'offset_scale': 0.0}, 'out of range'),
            ({'method': 'bogus'}, 'must be one of lln | holistic'),
            ({'mode': 'mapping'}, 'read-only'),
            ({'k': 2.5}, 'Wrong parameter type'),
            ({'sequence_max_gap': 0.0}, 'out of range'),
            ({'sequence_carry': -1}, 'out of range'),
            ({'sequence_acquire_k': -1}, 'out of range'),
            ({'sequence_acquire_k': 10**7}, 'out of range'),
            ({'sequence_acquire_k': 'many'}, 'Wrong parameter type'),
            ({'similarity': 'cosine'}, 'must be one of raw | center | whiten | fuse'),
            ({'sequence_score_norm': 'mean'}, 'must be one of zscore | none'),
        ):
            result = m.set(**values)[0]
            assert not result.successful and reason in result.reason, (values, result.reason)
        queries.publish(msgs.landmarks_to_cloud(places['sets'][5], msgs.make_header(T0 + 101 * 10**9)))
        m.probe.spin_until(lambda: len(answers) >= 2, 30, 'a second answer')
        assert len(answers[-1]) == 2  # k is still 2
        log = m.proc.log()  # SetParameters (not ..._atomically) applies them one at a time
        assert 'parameters changed: k=2' in log and 'parameters changed: min_score=0.5' in log
        # the reranker's S at run time: raw S (the paper's) scores the same query lower than the
        # default fused S (raw S + 2 x whitened S)
        fused_best = float(answers[-1]['score'].max())
        assert m.set(similarity='raw')[0].successful
        queries.publish(msgs.landmarks_to_cloud(places['sets'][5], msgs.make_header(T0 + 102 * 10**9)))
        m.probe.spin_until(lambda: len(answers) >= 3, 30, 'a raw answer')
        assert float(answers[-1]['score'].max()) < fused_best, (answers[-1], fused_best)
        assert m.set(similarity='fuse')[0].successful
        assert m.set(sequence_acquire_k=50)[0].successful  # run time, in range

        # WARN: queries older than max_query_age (set at run time) are dropped, and diagnostics say so
        assert m.set(max_query_age=5.0)[0].successful
        queries.publish(msgs.landmarks_to_cloud(places['sets'][1], msgs.make_header(T0)))  # 2023: years old
        m.wait_status(lambda s: s.level == DiagnosticStatus.WARN, 'WARN')
        assert 'older than max_query_age 5 s' in m.status.message and 'use_sim_time' in m.status.message
        m.wait_status(lambda s: s.level == DiagnosticStatus.OK, 'back to OK once nothing is dropped')

        # WARN: a best-effort landmark publisher cannot match the reliable query subscription
        from rclpy.qos import qos_profile_sensor_data

        m.probe.node.create_publisher(PointCloud2, 'lln/query', qos_profile_sensor_data)
        m.wait_status(lambda s: s.level == DiagnosticStatus.WARN and 'incompatible QoS' in s.message, 'QoS WARN')

        # ERROR: an extractor with another model: every landmark input is refused until they agree
        from lln_ros.nodes.common import MODEL_QOS  # latched, as the extractor's

        models = m.probe.node.create_publisher(String, 'lln/model_info', MODEL_QOS)
        other = {**places['model'], 'descriptor_space': 'efficientnet_lite2/stage6/192'}
        models.publish(String(data=json.dumps(other)))
        m.wait_status(lambda s: s.level == DiagnosticStatus.ERROR, 'ERROR')
        assert m.status.message.startswith('refusing all landmark input')
    finally:
        code = m.close()
    assert code == 0, m.proc.log()


def landmark_bag(tmp_path, places, count=12, rate=2.0):
    """A bag of real landmark clouds on /query at `rate` Hz (what a recorded extractor output is)."""
    stamps = bag.frame_stamps(count, rate)
    out = tmp_path / 'queries_bag'
    bag.write_bag(
        out,
        [
            ('/lln/query', msgs.landmarks_to_cloud(places['sets'][i % len(places['sets'])], msgs.make_header(s)), s)
            for i, s in enumerate(stamps)
        ],
    )
    return out, stamps


def replay(m: Matcher, bag_dir, rate, clock: bool, start_ns: int):
    """lln-bag play into the matcher, every hop linked before the first message goes out.
    A volatile DDS reader drops what a writer sent before the reader matched it, even when the
    writer had matched the reader already, and a sim-time matcher without the bag's clock yet
    judges a query by time 0. The player waits for two subscribers on /lln/query: the matcher
    and a gate of ours, opened only once the matcher counts the player's writer, runs on the bag's
    clock (with --clock) and our answer reader is matched at both ends."""
    answers = m.probe.collect(PointCloud2, 'lln/candidates', lambda c: (msgs.stamp_to_ns(c.header.stamp), c))
    play = subprocess.Popen(
        [
            sys.executable,
            '-m',
            'lln_ros.cli.bag',
            'play',
            str(bag_dir),
            '--wait-subscribers',
            '2',
            '--wait-timeout',
            '60',
            '--rate',
            str(rate),
            *(['--clock'] if clock else []),
        ],
        env=m.env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    ends: dict = {}
    deadline = time.monotonic() + 60
    while play.poll() is None:
        info = m.info()
        ends.update(
            query_reader=info['publishers']['query'],
            answer_writer=info['subscriptions']['candidates'],
            answer_reader=m.probe.matched_writers('lln/candidates'),
            matcher_clock=m.diag_stamp,
        )
        if min(ends[k] for k in ('query_reader', 'answer_writer', 'answer_reader')) >= 1:
            if not clock or m.diag_stamp >= start_ns:
                break
        assert time.monotonic() < deadline, f'hops not linked after 60 s: {ends}'
        m.probe.spin_for(0.1)
    gate = m.probe.node.create_subscription(PointCloud2, '/lln/query', lambda _m: None, 10)
    m.probe.spin_until(lambda: play.poll() is not None, 120, 'lln-bag play')
    m.probe.node.destroy_subscription(gate)
    out = play.stdout.read()
    assert play.returncode == 0, out
    return answers, out


@pytest.mark.parametrize('sim_time', [True, False])
def test_bag_replay_with_sim_time(colcon_install, tmp_path, places, sim_time):
    """6 s of recorded queries at 4x (1.5 s of wall time) with max_query_age 1 s. With sim time
    every query is answered at once: a matcher whose executor falls behind the bag (rclpy #1452,
    lln_ros.nodes.common.two_thread_executor) answers them late and counts them stale."""
    bag_dir, stamps = landmark_bag(tmp_path, places)
    m = Matcher(
        colcon_install,
        tmp_path,
        places,
        '-p',
        'mode:=mapping',
        '-p',
        'max_query_age:=1.0',
        '-p',
        f'use_sim_time:={str(sim_time).lower()}',
    )
    try:
        start = time.monotonic()
        answers, out = replay(m, bag_dir, 4.0, clock=sim_time, start_ns=stamps[0])
        if sim_time:
            try:
                m.probe.spin_until(lambda: len(answers) == len(stamps), 30, 'every answer')
            except Exception as e:
                got = f'{len(answers)} of {len(stamps)} answers; matcher: {m.values()}'
                raise AssertionError(f'{e}\n{got}\n{m.proc.log()[-3000:]}') from None
            assert time.monotonic() - start < 6.0 + 30  # faster than real time (+ discovery)
            assert [s for s, _ in answers] == stamps  # every query, in order, its stamp unchanged
            m.wait_status(lambda s: m.values().get('queries_answered') == str(len(stamps)), 'counters')
            v = m.values()
            assert 'queries_stale' not in v, v
            assert 0.0 <= float(v['last_query_age_s']) < 1.0, v  # bag time: ages are real, small
            # the diagnostics stamp is the node clock: bag time (2023), not wall time
            assert stamps[0] <= m.diag_stamp <= stamps[-1] + 2 * 10**9, (m.diag_stamp, stamps[-1])
        else:
            m.wait_status(lambda s: m.values().get('queries_stale') == str(len(stamps)), 'every query stale')
            assert not answers
            m.probe.spin_for(0.5)
            assert 'use_sim_time:=true' in m.proc.log()  # the WARN line says why
    finally:
        code = m.close()
    assert code == 0, m.proc.log()


def test_frame_queue_keeps_every_frame_of_a_burst(colcon_install, tmp_path, photo):
    """frame_queue 30 (for bag replays): a burst of 20 frames, far faster than extraction, is
    extracted completely, in order; the default (1) would keep only the newest waiting frame."""
    import cv2
    from sensor_msgs.msg import Image

    env = installed_env(colcon_install, ros_env(tmp_path))
    share = colcon_install / 'lln_ros' / 'share' / 'lln_ros'
    proc = RosProcess(
        colcon_install / 'lln_ros' / 'lib' / 'lln_ros' / 'extractor',
        [
            '--params-file',
            str(share / 'config' / 'extractor.yaml'),
            '-p',
            'frame_queue:=30',
            '-p',
            'reliability:=reliable',
            '-p',
            'num_threads:=1',
            '-p',
            'input_height:=128',
        ],
        env,
        tmp_path / 'extractor.log',
    )
    probe = Probe(env)
    try:
        images = probe.publisher(Image, 'image')
        got = probe.collect(PointCloud2, 'lln/landmarks', lambda c: msgs.stamp_to_ns(c.header.stamp))
        probe.spin_until(lambda: images.get_subscription_count() or not proc.alive(), 120, 'extractor')
        assert proc.alive(), proc.log()
        probe.spin_for(1.0)
        small = np.ascontiguousarray(cv2.resize(photo, (160, 188)))
        stamps = [T0 + i * 10**8 for i in range(20)]
        for s in stamps:
            images.publish(msgs.array_to_image(small, 'rgb8', msgs.make_header(s)))
        probe.spin_until(lambda: len(got) == len(stamps), 120, 'every frame extracted')
        assert got == stamps
    finally:
        probe.close()
        code = proc.stop()
    assert code == 0, proc.log()
