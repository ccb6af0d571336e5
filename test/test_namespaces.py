"""Two pipelines side by side on one DDS domain, each in its own namespace, as a fleet or a robot
with two cameras runs them (`ros2 launch lln_ros lln.launch.py namespace:=robot1`): every topic of
the nodes is relative (lln_ros.ros.topics), so /robot1/... and /robot2/... never meet. Real
executables (colcon-installed), real DDS, real images: each pipeline answers exactly its own
queries and stores exactly its own keyframes."""

from __future__ import annotations

import json
from functools import partial

import cv2
import numpy as np
from sensor_msgs.msg import Image, PointCloud2
from std_srvs.srv import Trigger
from test_nodes import TIMEOUT, header, rig  # noqa: F401  (rig: the fixture)

from lln_ros.ros import msgs, topics

ROBOTS = ('robot1', 'robot2')


def matcher_info(rig, ns: str) -> dict:
    return json.loads(rig.probe.call(Trigger, f'/{ns}/lln_matcher/info', timeout=TIMEOUT).message)


def wait_linked(rig, images: dict) -> None:
    """Wait until every hop of each robot's pipeline (us -> extractor -> matcher -> us) is matched
    at both ends. A DDS writer and reader match each on their own: a volatile reader drops what a
    writer sent before the reader matched it, even when the writer had matched the reader already.
    Both namespaced tests send a single frame per place, and a frame lost that way failed them
    about one run in three under load, until the test waited on the reader ends too."""

    ends: dict = {}

    def linked(ns: str) -> bool:
        extractor, matcher = rig.diag.get(f'/{ns}/lln_extractor', {}), matcher_info(rig, ns)
        ends[ns] = {
            'image writer': images[ns].get_subscription_count(),  # ours -> the extractor's reader
            'image reader': int(extractor.get('image_publishers', 0)),  # ... and that reader -> ours
            'landmark writer': int(extractor.get('landmark_subscribers', 0)),  # extractor -> matcher
            'landmark reader': matcher['publishers']['query'],  # ... and the matcher's reader
            'answer writer': matcher['subscriptions']['candidates'],  # matcher -> us
            'answer reader': rig.probe.matched_writers(f'/{ns}/{topics.CANDIDATES}'),  # ... and ours
        }
        return all(n == 1 for n in ends[ns].values())

    try:
        rig.until(lambda: all([linked(ns) for ns in ROBOTS]), 'both pipelines linked, every hop matched at both ends')
    except AssertionError as e:
        raise AssertionError(f'{e}\nmatched ends: {ends}') from None


def test_two_namespaced_pipelines_answer_only_their_own_queries(rig, photo, tmp_path):
    procs = {}
    for ns in ROBOTS:
        ros_ns = ['-r', f'__ns:=/{ns}']
        procs[ns, 'extractor'] = rig.extractor(*ros_ns, '-p', 'input_height:=128', '-p', 'top_n:=10')
        # what the launch file's feed:=query does: the extractor's landmarks are the matcher's queries
        procs[ns, 'matcher'] = rig.matcher(
            tmp_path / f'{ns}.db', *ros_ns, '-r', f'{topics.QUERY}:={topics.LANDMARKS}', '-p', 'mode:=mapping'
        )
    images = {ns: rig.probe.publisher(Image, f'/{ns}/{topics.IMAGE}') for ns in ROBOTS}
    answers = {
        ns: rig.probe.collect(PointCloud2, f'/{ns}/{topics.CANDIDATES}', lambda m: msgs.stamp_to_ns(m.header))
        for ns in ROBOTS
    }
    wait_linked(rig, images)
    # real frames: robot1 sees crops of the left of the photograph, robot2 of its right half
    h, w = photo.shape[:2]
    frames = {
        ns: [
            np.ascontiguousarray(photo[y : y + h // 2, x0 + dx : x0 + dx + w // 3]) for y, dx in ((0, 0), (h // 3, 20))
        ]
        for ns, x0 in zip(ROBOTS, (0, w // 2))
    }
    sent = {ns: [] for ns in ROBOTS}
    for i in range(2):
        for k, ns in enumerate(ROBOTS):
            hdr = header(10 * k + i, frame=f'{ns}_camera')
            images[ns].publish(msgs.array_to_image(cv2.resize(frames[ns][i], (160, 120)), 'rgb8', hdr))
            sent[ns].append(msgs.stamp_to_ns(hdr))
            rig.until(lambda ns=ns: len(answers[ns]) >= len(sent[ns]), f'{ns} answer {i}', procs[ns, 'matcher'])
    rig.probe.spin_for(1.0)  # a crossed answer would arrive by now
    for ns in ROBOTS:
        assert answers[ns] == sent[ns], f'{ns} answered stamps {answers[ns]}, it was sent {sent[ns]}'
        stored = matcher_info(rig, ns)
        assert stored['keyframes'] == len(sent[ns]) and stored['path'] == str(tmp_path / f'{ns}.db')
    for proc in procs.values():
        assert proc.alive()


def test_two_robots_map_into_one_map_and_close_loops_across_robots(rig, photo, tmp_path):
    """Issue 29: two robots (namespaces) mapping into one SQLite map at once. Each keyframe is
    stored under its robot's session; robot2 passing a place robot1 mapped a moment ago gets robot1's
    keyframe as its answer (exclude_recent applies to a robot's own session), named by session_id."""
    shared = tmp_path / 'fleet.db'
    procs = {}
    for ns in ROBOTS:
        ros_ns = ['-r', f'__ns:=/{ns}']
        procs[ns, 'extractor'] = rig.extractor(*ros_ns, '-p', 'input_height:=128', '-p', 'top_n:=10')
        procs[ns, 'matcher'] = rig.matcher(
            shared,
            *ros_ns,
            '-r',
            f'{topics.QUERY}:={topics.LANDMARKS}',
            '-p',
            'mode:=mapping',
            '-p',
            'exclude_recent:=10',
        )
    images = {ns: rig.probe.publisher(Image, f'/{ns}/{topics.IMAGE}') for ns in ROBOTS}
    answers = {ns: rig.probe.collect(PointCloud2, f'/{ns}/{topics.CANDIDATES}') for ns in ROBOTS}
    wait_linked(rig, images)
    info = partial(matcher_info, rig)
    h, w = photo.shape[:2]
    places = [np.ascontiguousarray(photo[y : y + h // 2, x : x + w // 3]) for y, x in ((0, 0), (h // 3, w // 2))]
    # robot1 maps both places; robot2 then passes the first one (the same view, 1 s later)
    for i, (ns, place) in enumerate((('robot1', 0), ('robot1', 1), ('robot2', 0))):
        images[ns].publish(msgs.array_to_image(cv2.resize(places[place], (160, 120)), 'rgb8', header(20 * i)))
        want = sum(1 for n, _ in ((('robot1', 0), ('robot1', 1), ('robot2', 0))[: i + 1]) if n == ns)
        try:
            rig.until(lambda ns=ns, want=want: len(answers[ns]) >= want, f'{ns} answer {i}', procs[ns, 'matcher'])
        except AssertionError as e:  # which hop lost it: what the matcher counted says
            raise AssertionError(f'{e}\n{ns} matcher: {info(ns)}') from None
    sessions = {s['robot']: s['id'] for s in info('robot2')['sessions']}
    assert set(sessions) == {'robot1', 'robot2'}
    mine = {ns: info(ns)['session'] for ns in ROBOTS}
    assert mine['robot1']['id'] == sessions['robot1'] and mine['robot1']['keyframes'] == 2
    assert mine['robot2']['id'] == sessions['robot2'] and mine['robot2']['keyframes'] == 1
    assert len(msgs.cloud_to_candidates(answers['robot1'][0])) == 0  # the map was empty
    loop = msgs.cloud_to_candidates(answers['robot2'][0])
    assert len(loop) and int(loop['keyframe_id'][0]) == 1 and int(loop['session_id'][0]) == sessions['robot1']
    for proc in procs.values():
        assert proc.alive()
