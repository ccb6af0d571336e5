"""The two nodes as users run them: the colcon-installed `extractor` and `matcher` executables as
separate processes, real DDS on a ROS domain of each test's own, a probe node on the test side.

Covers the node behaviours of issue 4 and its "Bad input and faults" list: every supported image
encoding, compressed transport, the activation image, bounded latency under a backlog; the map
server in localization and mapping mode, its services, bad clouds, a corrupt map, a map from another
model, a service call during a burst, and kill -9 in mapping mode (no acknowledged keyframe lost).

Landmark clouds for the matcher come from real extractions done once per module (the matplotlib
photograph, cropped into distinct "places"), so most matcher tests do not run the network.
"""

from __future__ import annotations

import array
import hashlib
import json
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from diagnostic_msgs.msg import DiagnosticArray
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CompressedImage, Image, PointCloud2
from std_srvs.srv import Trigger

from lln_ros.core.landmarks import LandmarkSet
from lln_ros.mapstore import MapStore
from lln_ros.ros import msgs
from ros_harness import Probe, RosProcess, installed_env, ros_env

TIMEOUT = 60.0  # generous: a loaded 2-core CI machine starts torch slowly
EXTRACTOR = '/lln_extractor'
MATCHER = '/lln_matcher'
DIM = 192  # descriptor size of the default model (efficientnet_lite0/stage6)
T0 = 1_700_000_000 * 10**9  # stamps of the test messages start here (ns)


# --------------------------------------------------------------------------------------------
# harness: one Rig per test = a domain, its processes, one probe, the latest /diagnostics


class Rig:
    def __init__(self, install: Path, tmp: Path):
        self.tmp = tmp
        self.lib = install / 'lln_ros' / 'lib' / 'lln_ros'
        self.config = install / 'lln_ros' / 'share' / 'lln_ros' / 'config'
        self.env = installed_env(install, ros_env(tmp))
        self.procs: list[RosProcess] = []
        self.diag: dict[str, dict[str, str]] = {}
        self.probe = Probe(self.env)
        self.probe.node.create_subscription(DiagnosticArray, '/diagnostics', self._on_diag, 50)

    def _on_diag(self, msg: DiagnosticArray) -> None:
        for status in msg.status:
            self.diag[status.name] = {kv.key: kv.value for kv in status.values}

    def start(self, exe: str, *ros_args: str, log: str | None = None) -> RosProcess:
        name = log or f'{exe}{len(self.procs)}'
        proc = RosProcess(self.lib / exe, list(ros_args), self.env, self.tmp / f'{name}.log')
        self.procs.append(proc)
        return proc

    def extractor(self, *ros_args: str) -> RosProcess:
        """The extractor with the packaged YAML, one torch thread and reliable images (overridable)."""
        return self.start(
            'extractor',
            '--params-file',
            str(self.config / 'extractor.yaml'),
            '-p',
            'num_threads:=1',
            '-p',
            'reliability:=reliable',
            '-p',
            'diagnostics_period:=0.2',
            *ros_args,
        )

    def matcher(self, map_path: Path, *ros_args: str) -> RosProcess:
        return self.start(
            'matcher',
            '--params-file',
            str(self.config / 'matcher.yaml'),
            '-p',
            f'map_path:={map_path}',
            '-p',
            'diagnostics_period:=0.2',
            *ros_args,
        )

    def counter(self, node: str, key: str) -> int:
        return int(self.diag.get(node, {}).get(key, 0))

    def wait_counter(
        self, node: str, key: str, value: int, proc: RosProcess | None = None, timeout: float = TIMEOUT
    ) -> None:
        self.until(lambda: self.counter(node, key) >= value, f'{node} {key} >= {value}', proc, timeout)

    def until(self, done, what: str, proc: RosProcess | None = None, timeout: float = TIMEOUT) -> None:
        """Spin the probe until done(); fail at once (with its log) if `proc` dies meanwhile."""

        def check():
            if proc is not None and not proc.alive():
                raise AssertionError(f'process died while waiting for {what}:\n{read_log(proc)}')
            return done()

        try:
            self.probe.spin_until(check, timeout, what)
        except TimeoutError as e:
            logs = '\n'.join(f'--- {p.log_path.name}\n{read_log(p)[-3000:]}' for p in self.procs)
            raise AssertionError(f'{e}\n{logs}') from None

    def call(self, service: str, timeout: float = TIMEOUT) -> Trigger.Response:
        """Call a matcher service, retrying: after a kill -9 the dead node's server lingers in
        discovery for a while and a request may go to it alone."""
        deadline = time.monotonic() + timeout
        while True:
            try:
                return self.probe.call(Trigger, f'{MATCHER}/{service}', timeout=5.0)
            except TimeoutError:
                if time.monotonic() > deadline:
                    raise

    def info(self) -> dict:
        response = self.call('info')
        assert response.success, response.message
        return json.loads(response.message)

    def answers_reach_us(self, proc: RosProcess, topics=('candidates',), timeout: float = TIMEOUT) -> None:
        """Wait until the matcher's answer publishers on `topics` have matched this probe's
        subscriptions (its ~/info `subscriptions`). Answers are volatile, and under load the matcher
        can discover the query publisher before the answer subscriptions: an answer sent in between
        is lost (a CI run failed so, 2026-12-02)."""

        def matched() -> bool:  # until() calls this between spins, so it may call the service
            subs = self.info().get('subscriptions', {})
            return all(subs.get(t, 0) > 0 for t in topics)

        self.until(matched, f'the matcher to match our {"/".join(topics)} subscriptions', proc, timeout)

    def close(self) -> None:
        for proc in self.procs:
            proc.stop()
        self.probe.close()


@pytest.fixture
def rig(colcon_install, tmp_path):
    r = Rig(colcon_install, tmp_path)
    yield r
    r.close()


def read_log(proc: RosProcess) -> str:
    """The process's stdout+stderr so far (works before and after it stopped)."""
    return proc.log_path.read_text(errors='replace')


def log_lines(proc: RosProcess, text: str) -> list[str]:
    return [line for line in read_log(proc).splitlines() if text in line]


def header(i: int, frame: str = 'cam') -> object:
    return msgs.make_header(T0 + i * 50_000_000 + 123, frame)


def same_header(a, b) -> bool:
    return msgs.stamp_to_ns(a) == msgs.stamp_to_ns(b) and a.frame_id == b.frame_id


def answers_header(table, sent) -> bool:
    """A table cloud (landmarks, candidates, matches, keypoints) answering `sent`: its stamp, and the
    frame that says it is a table (msgs.TABLE_FRAME), not the camera's."""
    return msgs.stamp_to_ns(table) == msgs.stamp_to_ns(sent) and table.frame_id == msgs.TABLE_FRAME


def stamp_of(h) -> tuple[int, int]:
    return int(h.stamp.sec), int(h.stamp.nanosec)


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# --------------------------------------------------------------------------------------------
# real landmark sets, extracted once per module


@pytest.fixture(scope='module')
def small_photo(photo) -> np.ndarray:
    """RGB 160x188: the real photograph at a size that keeps every extraction cheap."""
    return cv2.resize(photo, (160, 188), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope='module')
def places(extractor, photo) -> dict:
    """Fourteen distinct landmark sets (crops and flips of a real photograph) and their model."""
    crops = [photo[y : y + 256, x : x + 224] for y in (0, 170, 340) for x in (0, 144, 288)]
    crops += [c[:, ::-1] for c in crops[:3]] + [np.ascontiguousarray(c[::-1]) for c in crops[3:5]]
    sets = extractor.extract_batch([np.ascontiguousarray(c) for c in crops])
    return {
        'sets': sets,
        'space': extractor.model_info['descriptor_space'],
        'dim': extractor.model_info['descriptor_dim'],
        'model': extractor.model_info,
    }


def cloud(places, i: int, h) -> PointCloud2:
    return msgs.landmarks_to_cloud(places['sets'][i % len(places['sets'])], h)


def stored_stamps(map_path: Path) -> tuple[list, list]:
    """(stamps of every keyframe, MapStore.check() problems) of a map no process has open."""
    with MapStore(map_path, create=False) as store:
        stamps = [store.get(k).meta['stamp'] for k in store.ids()]
        return stamps, store.check()


# ============================================================================================
# extractor


def test_extractor_every_encoding(rig, small_photo):
    """rgb8, bgr8, mono8, rgba8, bgra8: one landmarks cloud each, header copied, row 0 = the whole
    image; the channel order is honoured (the same pixels in any colour layout give one descriptor)."""
    proc = rig.extractor()
    rgb = small_photo
    h, w = rgb.shape[:2]
    alpha = np.full((h, w, 1), 200, np.uint8)
    images = {
        'rgb8': rgb,
        'bgr8': rgb[:, :, ::-1],
        'mono8': cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY),
        'rgba8': np.concatenate([rgb, alpha], 2),
        'bgra8': np.concatenate([rgb[:, :, ::-1], alpha], 2),
    }
    got = rig.probe.collect(PointCloud2, 'lln/landmarks')
    pub = rig.probe.publisher(Image, 'image')
    rig.until(
        lambda: pub.get_subscription_count() > 0 and rig.probe.node.count_publishers('lln/landmarks') > 0,
        'extractor up',
        proc,
    )
    sent = {}
    for i, (enc, img) in enumerate(images.items()):
        hdr = header(i, frame=f'camera_{enc}')
        pub.publish(msgs.array_to_image(np.ascontiguousarray(img), enc, hdr))
        rig.until(lambda: len(got) > i, f'landmarks for {enc}', proc)  # one at a time: none dropped
        sent[enc] = hdr
    out = {}
    for enc, msg in zip(images, got):
        assert answers_header(msg.header, sent[enc]), (enc, msg.header, sent[enc])
        lset = msgs.cloud_to_landmarks(msg, expected_dim=DIM)
        assert tuple(lset.image_size) == (w, h), enc
        table = msgs.cloud_to_array(msg)
        assert (table['u'][0], table['v'][0], table['w'][0], table['h'][0]) == (w / 2, h / 2, w, h)
        assert list(table['score'][1:]) == sorted(table['score'][1:], reverse=True), 'rows 1..n by score'
        assert len(lset) == 50 and msg.height == 1 and msg.is_dense and not msg.is_bigendian
        out[enc] = lset.global_descriptor
    for enc in ('bgr8', 'rgba8', 'bgra8'):
        np.testing.assert_allclose(out[enc], out['rgb8'], atol=1e-5, err_msg=enc)
    assert not np.allclose(out['mono8'], out['rgb8'], atol=1e-5)
    rig.wait_counter(EXTRACTOR, 'published', 5, proc)
    assert rig.counter(EXTRACTOR, 'bad_image') == 0 and rig.counter(EXTRACTOR, 'dropped') == 0


def bad_images(w: int = 64, h: int = 48) -> dict:
    """Images the extractor must skip, by the text of the warning each one gets."""
    depth = Image(encoding='16UC1', width=w, height=h, step=2 * w, data=array.array('B', bytes(2 * w * h)))
    empty = Image(encoding='rgb8', width=0, height=0, step=0)
    truncated = msgs.array_to_image(np.zeros((h, w, 3), np.uint8), 'rgb8')
    truncated.data = array.array('B', bytes(truncated.data)[: w * h])
    tiny = msgs.array_to_image(np.zeros((4, 4, 3), np.uint8), 'rgb8')
    return {
        "unsupported encoding '16UC1'": depth,
        'empty image (0x0)': empty,
        'data is truncated': truncated,
        'image is 4x4 pixels': tiny,
    }


def test_extractor_skips_bad_images(rig, small_photo):
    """Wrong encoding, zero size, truncated data, too small: skipped, counted in /diagnostics,
    each distinct problem logged once (as a warning), and the next good image is answered."""
    proc = rig.extractor()
    got = rig.probe.collect(PointCloud2, 'lln/landmarks')
    pub = rig.probe.publisher(Image, 'image')
    rig.until(lambda: pub.get_subscription_count() > 0, 'extractor up', proc)
    bad = bad_images()
    n = 0
    for _ in range(2):  # twice each: counted twice, logged once
        for i, msg in enumerate(bad.values()):
            msg.header = header(100 + n)
            pub.publish(msg)
            n += 1
            rig.wait_counter(EXTRACTOR, 'bad_image', n, proc)
    good = header(7, 'good')
    pub.publish(msgs.array_to_image(small_photo, 'rgb8', good))
    rig.until(lambda: len(got) == 1, 'the good image after the bad ones', proc)
    assert answers_header(got[0].header, good)
    rig.wait_counter(EXTRACTOR, 'published', 1, proc)
    assert rig.counter(EXTRACTOR, 'bad_image') == 2 * len(bad)
    assert rig.counter(EXTRACTOR, 'received') == 2 * len(bad) + 1
    for text in bad:
        lines = log_lines(proc, text)
        assert len(lines) == 1, (text, read_log(proc))
        assert 'WARN' in lines[0] and 'bad_image' in lines[0]
    assert proc.alive()


def test_extractor_compressed_transport(rig, photo):
    """image_transport=compressed: jpeg and png on image/compressed, with the default sensor-data
    (best-effort) subscription and a camera-like best-effort publisher; undecodable data skipped."""
    proc = rig.extractor(
        '-p',
        'image_transport:=compressed',
        '-p',
        'reliability:=best_effort',
        '-p',
        'input_height:=128',
        '-p',
        'top_n:=10',
    )
    got = rig.probe.collect(PointCloud2, 'lln/landmarks')
    pub = rig.probe.node.create_publisher(CompressedImage, 'image/compressed', qos_profile_sensor_data)
    rig.until(lambda: pub.get_subscription_count() > 0, 'extractor up', proc)
    bgr = cv2.resize(photo, (200, 150))[:, :, ::-1]
    garbage = CompressedImage(format='jpeg', data=array.array('B', b'\xff\xd8\xff' + bytes(range(256)) * 4))
    frames = [
        ('jpeg', msgs.array_to_compressed(bgr, fmt='jpeg', quality=80)),
        ('garbage', garbage),
        ('png', msgs.array_to_compressed(bgr, fmt='png')),
    ]
    for i, (fmt, msg) in enumerate(frames):
        msg.header = header(i, 'cam_' + fmt)
        deadline = time.monotonic() + TIMEOUT
        while True:  # best effort may lose a sample: resend until it is accounted for
            pub.publish(msg)
            try:
                if fmt == 'garbage':
                    rig.wait_counter(EXTRACTOR, 'bad_image', 1, proc, timeout=1.0)
                else:
                    rig.until(lambda: any(answers_header(m.header, msg.header) for m in got), fmt, proc, 1.0)
                break
            except AssertionError:
                if time.monotonic() > deadline or not proc.alive():
                    raise
    for i, (fmt, _) in enumerate(frames):
        if fmt not in ('jpeg', 'png'):
            continue
        m = next(m for m in got if msgs.stamp_to_ns(m.header) == msgs.stamp_to_ns(header(i)))
        lset = msgs.cloud_to_landmarks(m, expected_dim=DIM)
        assert tuple(lset.image_size) == (200, 150) and len(lset) == 10
    assert len(log_lines(proc, 'cannot decode')) == 1
    assert proc.alive()


def test_extractor_activation_image(rig, small_photo):
    """publish_activation: a bgr8 heatmap of the input's size, with the input's header."""
    proc = rig.extractor('-p', 'publish_activation:=true', '-p', 'input_height:=128')
    heat = rig.probe.collect(Image, 'lln/activation')
    got = rig.probe.collect(PointCloud2, 'lln/landmarks')
    pub = rig.probe.publisher(Image, 'image')
    rig.until(
        lambda: pub.get_subscription_count() > 0 and rig.probe.node.count_publishers('lln/activation') > 0,
        'extractor up',
        proc,
    )
    hdr = header(3, 'act')
    pub.publish(msgs.array_to_image(small_photo, 'rgb8', hdr))
    rig.until(lambda: heat and got, 'activation and landmarks', proc)
    img = heat[0]
    h, w = small_photo.shape[:2]
    assert (img.encoding, img.width, img.height) == ('bgr8', w, h)
    assert same_header(img.header, hdr) and answers_header(got[0].header, hdr)
    arr, order = msgs.image_to_array(img)
    assert arr.shape == (h, w, 3) and order == 'bgr' and arr.std() > 0


def test_extractor_backlog_keeps_newest(rig, photo):
    """A burst faster than extraction: bounded output, `dropped` > 0, newest frame processed, and
    every received frame is either published or counted as dropped."""
    proc = rig.extractor('-p', 'input_height:=480')  # ~0.1-0.2 s per frame on one thread
    got = rig.probe.collect(PointCloud2, 'lln/landmarks')
    pub = rig.probe.publisher(Image, 'image')
    rig.until(lambda: pub.get_subscription_count() > 0, 'extractor up', proc)
    image = msgs.array_to_image(cv2.resize(photo, (320, 240)), 'rgb8')
    burst = 20
    for i in range(burst):
        image.header = header(i, 'burst')
        pub.publish(image)
    last = header(burst - 1, 'burst')
    rig.until(lambda: any(answers_header(m.header, last) for m in got), 'the newest frame', proc)
    rig.probe.spin_for(0.5)
    stamps = [msgs.stamp_to_ns(m.header) for m in got]
    assert stamps[-1] == msgs.stamp_to_ns(last) and stamps == sorted(stamps)
    assert len(got) < burst / 2, f'{len(got)} of {burst} processed: the backlog was not bounded'
    rig.until(lambda: rig.counter(EXTRACTOR, 'published') == len(got), 'diagnostics', proc)
    received, dropped = rig.counter(EXTRACTOR, 'received'), rig.counter(EXTRACTOR, 'dropped')
    assert dropped > 0
    assert received == dropped + len(got)


# ============================================================================================
# matcher


def start_matcher(rig, map_path, places, *args) -> RosProcess:
    proc = rig.matcher(map_path, '-p', f'descriptor_space:={places["space"]}', *args)
    rig.until(
        lambda: (
            rig.probe.node.count_publishers('lln/candidates') > 0
            and rig.probe.node.count_subscribers('lln/keyframes') > 0
        ),
        'matcher up',
        proc,
    )
    return proc


def test_matcher_localization(rig, places, tmp_path):
    """Keyframes are stored; a query equal to one of them gets it as top candidate with its stamp
    (header = the query's, scores descending, matches of the best candidate); the map is unchanged."""
    map_path = tmp_path / 'map.db'
    proc = start_matcher(rig, map_path, places, '-p', 'k:=3')
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates')
    matches = rig.probe.collect(PointCloud2, 'lln/matches')
    rig.until(lambda: kf_pub.get_subscription_count() > 0 and q_pub.get_subscription_count() > 0, 'subscriptions', proc)
    rig.answers_reach_us(proc, ('candidates', 'matches'))
    n = 8
    for i in range(n):
        kf_pub.publish(cloud(places, i, header(i, 'map')))
    rig.wait_counter(MATCHER, 'keyframes_stored', n, proc)
    before = rig.info()
    assert before['keyframes'] == n and before['mode'] == 'localization'
    target = 5
    qh = header(1000, 'query')
    q_pub.publish(cloud(places, target, qh))
    rig.until(lambda: cands and matches, 'the answer', proc)
    assert answers_header(cands[0].header, qh) and answers_header(matches[0].header, qh)
    table = msgs.cloud_to_candidates(cands[0])
    assert 1 <= len(table) <= 3
    assert (int(table['stamp_sec'][0]), int(table['stamp_nanosec'][0])) == stamp_of(header(target, 'map'))
    assert list(table['score']) == sorted(table['score'], reverse=True)
    pairs = msgs.cloud_to_matches(matches[0])
    assert len(pairs) > 0 and set(pairs['keyframe_id']) == {int(table['keyframe_id'][0])}
    np.testing.assert_allclose(pairs['query_u'], pairs['map_u'])  # the same image: regions coincide
    rig.probe.spin_for(0.3)
    after = rig.info()
    assert after['keyframes'] == n and after['last_id'] == before['last_id']
    assert after['counters']['queries_answered'] == 1
    assert proc.stop() == 0, read_log(proc)
    stamps, problems = stored_stamps(map_path)
    assert stamps == [stamp_of(header(i, 'map')) for i in range(n)] and problems == []


def test_matcher_min_score_new_place(rig, places, tmp_path):
    """A map built offline (MapStore) is served as it is; with a high min_score nothing passes, so
    the answer has zero rows ("new place") and so does `matches`."""
    map_path = tmp_path / 'map.db'
    with MapStore(map_path, model=places['model']) as store:
        for i in range(4):
            store.add(places['sets'][i], stamp=stamp_of(header(i)))
    proc = start_matcher(rig, map_path, places, '-p', 'min_score:=1000000.0')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates')
    matches = rig.probe.collect(PointCloud2, 'lln/matches')
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
    rig.answers_reach_us(proc, ('candidates', 'matches'))
    qh = header(50, 'query')
    q_pub.publish(cloud(places, 2, qh))
    rig.until(lambda: cands and matches, 'the answer', proc)
    assert answers_header(cands[0].header, qh)
    assert len(msgs.cloud_to_candidates(cands[0])) == 0 and cands[0].width == 0
    assert len(msgs.cloud_to_matches(matches[0])) == 0
    assert rig.info()['keyframes'] == 4


@pytest.mark.parametrize('novelty', [None, 0.0], ids=['default_novelty', 'novelty_off'])
def test_matcher_mapping_mode_exclude_recent(rig, places, tmp_path, novelty):
    """mode=mapping: every query is answered; the newest exclude_recent keyframes are never answers,
    an older revisit is found. With novelty off every query is stored; at the shipped
    keyframe_novelty_max_score the revisit (S above it: the place is in the map) is not."""
    map_path = tmp_path / 'map.db'
    novelty_args = () if novelty is None else ('-p', f'keyframe_novelty_max_score:={novelty}')
    proc = start_matcher(rig, map_path, places, '-p', 'mode:=mapping', '-p', 'exclude_recent:=2', *novelty_args)
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates', msgs.cloud_to_candidates)
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
    rig.answers_reach_us(proc)
    sequence = [0, 1, 2, 3, 4, 1, 5]  # frame 5 revisits place 1 (stored as keyframe 2)
    for j, place in enumerate(sequence):
        q_pub.publish(cloud(places, place, header(j)))
        rig.until(lambda: len(cands) > j, f'answer {j}', proc)
    assert [len(c) for c in cands[:3]] == [0, 0, 0]  # the map is empty or all of it too recent
    for j, c in enumerate(cands):
        allowed = {stamp_of(header(i)) for i in range(j - 2)}
        assert {(int(s), int(n)) for s, n in zip(c['stamp_sec'], c['stamp_nanosec'])} <= allowed, j
    revisit = cands[5]
    assert (int(revisit['stamp_sec'][0]), int(revisit['stamp_nanosec'][0])) == stamp_of(header(1))
    info = rig.info()
    revisits_kept_out = 0 if novelty == 0.0 else 1
    assert info['keyframes'] == len(sequence) - revisits_kept_out and info['mode'] == 'mapping'
    assert info['counters']['queries_answered'] == len(sequence)
    assert info['counters'].get('queries_not_stored', 0) == revisits_kept_out


def bad_clouds(places) -> dict:
    """Landmark clouds the matcher must refuse, by the text of the warning each one gets."""
    good = cloud(places, 0, header(0))
    table = msgs.cloud_to_array(good)
    no_score = np.zeros(len(table), [(n, '<f4') for n in 'uvwh'] + [('descriptor', '<f4', (places['dim'],))])
    for name in no_score.dtype.names:
        no_score[name] = table[name]
    wrong_d = np.zeros(len(table), [(n, '<f4') for n in ('u', 'v', 'w', 'h', 'score')] + [('descriptor', '<f4', (64,))])
    for name in 'uvwh':
        wrong_d[name] = table[name]
    wrong_d['score'] = table['score']
    wrong_d['descriptor'] = table['descriptor'][:, :64]
    nan = table.copy()
    nan['descriptor'][3, 7] = np.nan
    truncated = cloud(places, 0, header(0))
    truncated.data = array.array('B', bytes(truncated.data)[:-100])
    return {
        "required field 'score' is missing": msgs.array_to_cloud(no_score),
        f'descriptors have D=64, expected D={places["dim"]}': msgs.array_to_cloud(wrong_d),
        'descriptors contain NaN or inf': msgs.array_to_cloud(nan),
        'data is truncated': truncated,
    }


def test_matcher_refuses_bad_clouds(rig, places, tmp_path):
    """Missing fields, wrong D, NaN descriptors, truncated data on `keyframes` and `query`: each
    distinct problem logged once, every one counted, the node keeps running and keeps every
    keyframe it stored; a good query afterwards is answered."""
    map_path = tmp_path / 'map.db'
    proc = start_matcher(rig, map_path, places)
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes')
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    cands = rig.probe.collect(PointCloud2, 'lln/candidates')
    rig.until(lambda: kf_pub.get_subscription_count() > 0 and q_pub.get_subscription_count() > 0, 'subscriptions', proc)
    rig.answers_reach_us(proc)
    bad = bad_clouds(places)
    kf_pub.publish(cloud(places, 0, header(0)))
    rig.wait_counter(MATCHER, 'keyframes_stored', 1, proc)
    n = 0
    for rep in range(2):
        for msg in bad.values():
            msg.header = header(10 + n)
            kf_pub.publish(msg)
            n += 1
            rig.wait_counter(MATCHER, 'bad_keyframe', n, proc)
        kf_pub.publish(cloud(places, 1 + rep, header(1 + rep)))
        rig.wait_counter(MATCHER, 'keyframes_stored', 2 + rep, proc)
    for i, msg in enumerate(bad.values()):
        msg.header = header(50 + i)
        q_pub.publish(msg)
        rig.wait_counter(MATCHER, 'bad_query', i + 1, proc)
    qh = header(99, 'query')
    q_pub.publish(cloud(places, 1, qh))
    rig.until(lambda: cands, 'an answer to the good query', proc)
    top = msgs.cloud_to_candidates(cands[0])
    assert (int(top['stamp_sec'][0]), int(top['stamp_nanosec'][0])) == stamp_of(header(1))
    info = rig.info()
    assert info['keyframes'] == 3
    assert info['counters']['bad_keyframe'] == 2 * len(bad) and info['counters']['bad_query'] == len(bad)
    for text in bad:
        lines = log_lines(proc, text)
        assert len(lines) == 2, (text, read_log(proc))  # once as bad_keyframe, once as bad_query
        assert all('WARN' in line for line in lines)
    assert proc.alive()
    assert proc.stop() == 0
    stamps, problems = stored_stamps(map_path)
    assert stamps == [stamp_of(header(i)) for i in range(3)] and problems == []


def test_matcher_services(rig, places, tmp_path):
    """~/info (JSON: keyframes, model, map path, mode, counters), ~/save (checkpoint: WAL emptied),
    ~/clear (no keyframes; ids are not reused)."""
    map_path = tmp_path / 'sub dir' / 'map.db'
    proc = start_matcher(rig, map_path, places)
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes')
    rig.until(lambda: kf_pub.get_subscription_count() > 0, 'subscription', proc)
    empty = rig.info()
    assert empty['keyframes'] == 0 and empty['path'] == str(map_path)
    assert empty['model']['descriptor_space'] == places['space'] and empty['descriptor_dim'] == places['dim']
    for i in range(3):
        kf_pub.publish(cloud(places, i, header(i)))
    rig.wait_counter(MATCHER, 'keyframes_stored', 3, proc)
    info = rig.info()
    assert (info['keyframes'], info['first_id'], info['last_id']) == (3, 1, 3) and info['wal_bytes'] > 0
    saved = rig.call('save')
    assert saved.success and str(map_path) in saved.message and '3 keyframes' in saved.message
    assert rig.info()['wal_bytes'] == 0
    cleared = rig.call('clear')
    assert cleared.success and str(map_path) in cleared.message
    assert rig.info()['keyframes'] == 0
    kf_pub.publish(cloud(places, 4, header(4)))
    rig.wait_counter(MATCHER, 'keyframes_stored', 4, proc)
    info = rig.info()
    assert (info['keyframes'], info['first_id']) == (1, 4)
    assert proc.stop() == 0
    stamps, problems = stored_stamps(map_path)
    assert stamps == [stamp_of(header(4))] and problems == []


def test_matcher_service_calls_during_burst(rig, places, tmp_path):
    """~/info and ~/save called while a burst of keyframes arrives: every call is answered, no
    keyframe is lost."""
    map_path = tmp_path / 'map.db'
    proc = start_matcher(rig, map_path, places)
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes', depth=100)
    rig.until(lambda: kf_pub.get_subscription_count() > 0, 'subscription', proc)
    clients = {name: rig.probe.node.create_client(Trigger, f'{MATCHER}/{name}') for name in ('info', 'save')}
    rig.until(lambda: all(c.service_is_ready() for c in clients.values()), 'services', proc)
    burst = 60
    futures = []
    for i in range(burst):
        kf_pub.publish(cloud(places, i, header(i)))
        if i % 10 == 5:
            futures += [c.call_async(Trigger.Request()) for c in clients.values()]
            rig.probe.spin_for(0.0)
    rig.until(lambda: all(f.done() for f in futures), 'every service answer', proc, timeout=30)
    assert all(f.result().success for f in futures)
    counts = [json.loads(f.result().message)['keyframes'] for f in futures[0::2]]
    assert counts == sorted(counts) and counts[-1] <= burst
    rig.wait_counter(MATCHER, 'keyframes_stored', burst, proc)
    assert rig.info()['keyframes'] == burst
    assert proc.stop() == 0
    stamps, problems = stored_stamps(map_path)
    assert stamps == [stamp_of(header(i)) for i in range(burst)] and problems == []


def corrupt(kind: str, path: Path, places) -> None:
    if kind == 'garbage':
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 20000, np.uint8).tobytes())
        return
    with MapStore(path, model=places['model']) as store:
        for i in range(6):
            store.add(places['sets'][i], stamp=stamp_of(header(i)))
        store.save()
    data = bytearray(path.read_bytes())
    if kind == 'truncated':
        del data[len(data) // 2 :]
    elif kind == 'damaged_pages':  # every b-tree page header after the first page overwritten
        for page in range(1, len(data) // 4096):
            data[page * 4096 : page * 4096 + 64] = b'\xa5' * 64
    path.write_bytes(bytes(data))


@pytest.mark.parametrize('kind', ['garbage', 'truncated', 'damaged_pages'])
def test_matcher_corrupt_map_exits_and_leaves_file(rig, places, tmp_path, kind):
    """A corrupt map file: the node exits non-zero with an error naming the file, and the file is
    left exactly as it was (never replaced by an empty map)."""
    map_path = tmp_path / 'map.db'
    corrupt(kind, map_path, places)
    before = sha(map_path)
    proc = rig.matcher(map_path)
    deadline = time.monotonic() + TIMEOUT
    while proc.alive() and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not proc.alive(), f'the matcher kept running on a corrupt map:\n{read_log(proc)}'
    assert proc.proc.returncode != 0
    text = read_log(proc)
    assert str(map_path) in text and ('corrupt' in text or 'truncated' in text or 'not an SQLite' in text), text
    assert 'FATAL' in text and 'cannot start' in text and 'Traceback' not in text, text
    assert sha(map_path) == before


@pytest.mark.parametrize('other_dim', [8, DIM])
def test_matcher_refuses_other_model(rig, places, tmp_path, small_photo, other_dim):
    """A map made with another model ('x/y/D'): a cloud of another size is refused by the D check;
    once the extractor's latched model_info arrives, its keyframes are refused with an error naming
    both models, also when D happens to agree (only model_info can tell those spaces apart).
    The map is left as it was."""
    map_path = tmp_path / 'map.db'
    space = f'x/y/{other_dim}'
    other = {'descriptor_space': space, 'descriptor_dim': other_dim}
    rng = np.random.default_rng(1)

    def unit(*shape):
        x = rng.standard_normal(shape).astype(np.float32)
        return x / np.linalg.norm(x, axis=-1, keepdims=True)

    with MapStore(map_path, model=other) as store:
        store.add(
            LandmarkSet(
                global_descriptor=unit(other_dim),
                descriptors=unit(2, other_dim),
                cells=np.array([[0, 0], [1, 0]]),
                centers=np.array([[16, 16], [48, 16]], np.float32),
                scores=np.ones(2, np.float32),
                cell_size=np.array([32, 32], np.float32),
                image_size=np.array([64, 32], np.float32),
                grid=(1, 2),
                descriptor_space=space,
            ),
            stamp=(5, 6),
        )
    matcher = rig.matcher(map_path)
    kf_pub = rig.probe.publisher(PointCloud2, 'lln/keyframes')
    rig.until(lambda: kf_pub.get_subscription_count() > 0, 'matcher up', matcher)
    refused = 0
    if other_dim != places['dim']:
        kf_pub.publish(cloud(places, 0, header(0)))
        refused += 1
        rig.wait_counter(MATCHER, 'bad_keyframe', refused, matcher)
        assert len(log_lines(matcher, f'D={places["dim"]}, expected D={other_dim}')) == 1, read_log(matcher)

    extractor = rig.extractor('-p', 'input_height:=128', '-r', 'lln/landmarks:=lln/keyframes')
    rig.until(lambda: log_lines(matcher, places['space']), "the refusal of the extractor's model", matcher)
    refusal = log_lines(matcher, places['space'])[0]
    assert 'ERROR' in refusal and space in refusal and str(map_path) in refusal, refusal
    img_pub = rig.probe.publisher(Image, 'image')
    rig.until(lambda: img_pub.get_subscription_count() > 0, 'extractor up', extractor)
    for i in range(2):
        img_pub.publish(msgs.array_to_image(small_photo, 'rgb8', header(1 + i)))
        rig.wait_counter(EXTRACTOR, 'published', 1 + i, extractor)
    rig.wait_counter(MATCHER, 'bad_keyframe', refused + 2, matcher)
    info = rig.info()
    assert info['keyframes'] == 1 and info['descriptor_space'] == space
    assert 'keyframes_stored' not in info['counters']
    warnings = [line for line in log_lines(matcher, '[WARN]') if '[lln_matcher]' in line]
    assert len(warnings) == (1 if refused else 0) + 1, ('each distinct problem logged once', warnings)
    assert matcher.alive() and extractor.alive()
    assert matcher.stop() == 0
    with MapStore(map_path, create=False) as store:
        assert len(store) == 1 and store.model == other and store.check() == []


def test_matcher_kill9_in_mapping_mode_loses_no_answered_keyframe(rig, places, tmp_path):
    """kill -9 during a stream of queries in mapping mode: every keyframe whose answer was received
    is in the map after the crash, the map is healthy, and a restarted node serves all of it."""
    map_path = tmp_path / 'map.db'
    # novelty off: every answered query is a keyframe, so every answer names one that must survive
    args = ('-p', 'mode:=mapping', '-p', 'exclude_recent:=3', '-p', 'k:=3', '-p', 'keyframe_novelty_max_score:=0.0')
    proc = start_matcher(rig, map_path, places, *args)
    q_pub = rig.probe.publisher(PointCloud2, 'lln/query')
    answered = rig.probe.collect(PointCloud2, 'lln/candidates', lambda m: stamp_of(m.header))
    rig.until(lambda: q_pub.get_subscription_count() > 0, 'subscription', proc)
    rig.answers_reach_us(proc)
    # The stream runs until the kill, whatever the load: it is paced by the answers (at most 4
    # queries unanswered, far below queue_depth, so none is dropped and the map has no gaps) and
    # the node is killed as soon as 15 answers are in, with queries still in flight.
    published, deadline = 0, time.monotonic() + 120
    while len(answered) < 15 and time.monotonic() < deadline:
        if published - len(answered) < 4:
            q_pub.publish(cloud(places, published, header(published)))
            published += 1
        rig.probe.spin_for(0.02)
    proc.kill9()
    assert len(answered) >= 15, f'{len(answered)} answers in 120 s'
    rig.probe.spin_for(0.5)  # answers already on the wire
    assert not proc.alive() and len(answered) >= 15
    stamps, problems = stored_stamps(map_path)
    assert problems == []
    assert set(answered) <= set(stamps), f'answered but lost: {sorted(set(answered) - set(stamps))}'
    assert stamps == [stamp_of(header(i)) for i in range(len(stamps))]  # in order, no gaps

    restarted = start_matcher(rig, map_path, places, *args)
    info = rig.info()
    assert info['keyframes'] == len(stamps) and info['last_id'] == len(stamps)
    assert restarted.stop() == 0, restarted.log()


# ============================================================================================
# launch file (launch / launch_ros are not installable here: check it statically)


def test_launch_file_is_installed_and_consistent(colcon_install):
    """launch/lln.launch.py is installed to share/lln_ros/launch, compiles, declares the image and
    mode arguments, and starts both executables under the node names the packaged YAML files use."""
    import ast

    import yaml

    share = colcon_install / 'lln_ros' / 'share' / 'lln_ros'
    source = (share / 'launch' / 'lln.launch.py').read_text()
    tree = ast.parse(source)
    compile(tree, 'lln.launch.py', 'exec')
    calls = [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)]
    declared = {n.args[0].value for n in calls if n.func.id == 'DeclareLaunchArgument'}
    assert {'image', 'mode', 'image_transport', 'map_path'} <= declared
    used = {n.args[0].value for n in calls if n.func.id == 'LaunchConfiguration'}
    assert used <= declared, f'undeclared launch arguments: {used - declared}'
    from test_launch import keywords  # a call's keywords with `**ours` expanded

    nodes = [
        {k: v.value for k, v in keywords(n, tree).items() if isinstance(v, ast.Constant)}
        for n in calls
        if n.func.id == 'Node'
    ]
    for exe, name in (('extractor', 'lln_extractor'), ('matcher', 'lln_matcher')):
        assert {'package': 'lln_ros', 'executable': exe, 'name': name}.items() <= next(
            n for n in nodes if n.get('executable') == exe
        ).items()
        assert (colcon_install / 'lln_ros' / 'lib' / 'lln_ros' / exe).is_file()
        config = yaml.safe_load((share / 'config' / f'{exe}.yaml').read_text())
        assert list(config) == [name]
    assert any(isinstance(n, ast.FunctionDef) and n.name == 'generate_launch_description' for n in tree.body)
