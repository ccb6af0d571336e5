"""lln_ros.ros.bag and lln-bag: MCAP bags from image folders, read back with rosbags and with the
`mcap` reader, `info`, and `play` into a real subscriber in another process (real rclpy, real DDS)."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CompressedImage, Image

from lln_ros.cli.bag import main
from lln_ros.errors import ImageError
from lln_ros.io.datasets import natural_key
from lln_ros.ros import bag, msgs
from ros_harness import ros_env

DATA = Path(__file__).resolve().parents[2] / 'shared' / 'data'
RTABMAP = DATA / 'rtabmap_loop'
PY = sys.executable


def make_images(folder: Path, count: int = 12, size=(64, 48), suffix='.png') -> list[Path]:
    """Distinct, deterministic images named 1..count (so natural and text order differ)."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    paths = []
    for i in range(1, count + 1):
        coarse = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)  # smooth, so jpeg stays close
        image = cv2.resize(coarse, size, interpolation=cv2.INTER_LINEAR)
        cv2.putText(image, str(i), (2, size[1] - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2)
        path = folder / f'{i}{suffix}'
        assert cv2.imwrite(str(path), image)
        paths.append(path)
    return paths


def cli(*args) -> int:
    return main([str(a) for a in args])


def mcap_messages(bag_dir: Path) -> list:
    """(schema name, schema encoding, topic, message encoding, log_time, data) via the mcap package."""
    from mcap.reader import make_reader

    files = sorted(bag_dir.glob('*.mcap'))
    assert len(files) == 1, files
    with open(files[0], 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        out = [
            (s.name, s.encoding, c.topic, c.message_encoding, m.log_time, bytes(m.data))
            for s, c, m in reader.iter_messages(log_time_order=True)
        ]
    assert summary.statistics.message_count == len(out)
    return out


# ---------------------------------------------------------------- from-images


def test_natural_sort_and_list_images(tmp_path):
    make_images(tmp_path, 12)
    (tmp_path / 'notes.txt').write_text('not an image')
    names = [p.name for p in bag.list_images(tmp_path)]
    assert names == [f'{i}.png' for i in range(1, 13)]
    assert sorted(['a10.png', 'a2.png', 'a1.png', 'b.png'], key=natural_key) == ['a1.png', 'a2.png', 'a10.png', 'b.png']
    assert [p.name for p in bag.list_images(tmp_path, '1*.png')] == ['1.png', '10.png', '11.png', '12.png']


def test_from_images_raw_roundtrip(tmp_path, capsys):
    paths = make_images(tmp_path / 'imgs', 12)
    out = tmp_path / 'bag'
    assert cli('from-images', tmp_path / 'imgs', out, '--fps', 4, '--frame-id', 'cam0') == 0
    assert 'wrote 12 images' in capsys.readouterr().out
    # rosbags + rclpy deserialisation
    got = list(bag.read_messages(out))
    assert len(got) == 12
    step = 250_000_000
    for i, ((topic, msg, stamp), path) in enumerate(zip(got, paths)):
        assert topic == '/camera/image_raw' and isinstance(msg, Image)
        assert stamp == bag.DEFAULT_START_NS + i * step == msgs.stamp_to_ns(msg.header)
        assert msg.header.frame_id == 'cam0' and msg.encoding == 'rgb8'
        array, order = msgs.image_to_array(msg)
        np.testing.assert_array_equal(array, cv2.imread(str(path))[:, :, ::-1])
        assert order == 'rgb'
    # the mcap package reads it independently: a valid MCAP with ROS 2 schemas
    records = mcap_messages(out)
    assert [r[:4] for r in records] == [('sensor_msgs/msg/Image', 'ros2msg', '/camera/image_raw', 'cdr')] * 12
    assert [r[4] for r in records] == [bag.DEFAULT_START_NS + i * step for i in range(12)]
    for (_, msg, _), record in zip(got, records):
        again = deserialize_message(record[5], Image)
        assert bytes(again.data) == bytes(msg.data)


def test_from_images_compressed(tmp_path):
    paths = make_images(tmp_path / 'imgs', 5, suffix='.jpg')
    out = tmp_path / 'bag'
    stamps = bag.write_image_bag(
        paths, out, topic='/cam/compressed', rate=30.0, compressed=True, start_ns=5_000_000_123
    )
    assert stamps[0] == 5_000_000_123 and stamps[1] - stamps[0] == 33_333_333
    got = list(bag.read_messages(out))
    assert [t for t, _, _ in got] == ['/cam/compressed'] * 5
    for (topic, msg, stamp), path in zip(got, paths):
        assert isinstance(msg, CompressedImage) and msg.format == 'jpeg'
        bgr, order = msgs.compressed_to_array(msg)
        assert order == 'bgr'
        assert np.abs(bgr.astype(int) - cv2.imread(str(path)).astype(int)).mean() < 4  # jpeg re-encoded
    assert {r[0] for r in mcap_messages(out)} == {'sensor_msgs/msg/CompressedImage'}


def test_info(tmp_path, capsys):
    make_images(tmp_path / 'imgs', 6)
    out = tmp_path / 'bag'
    assert cli('from-images', tmp_path / 'imgs', out, '--rate', 2, '--start', 100) == 0
    capsys.readouterr()
    assert cli('info', out) == 0
    text = capsys.readouterr().out
    assert 'messages:  6' in text and 'duration:  2.500 s' in text and 'storage:   mcap' in text
    assert '/camera/image_raw' in text and 'sensor_msgs/msg/Image' in text
    assert 'start:     100.000000000' in text and 'end:       102.500000000' in text
    assert cli('info', out, '--json') == 0
    info = json.loads(capsys.readouterr().out)
    assert info['topics'] == {'/camera/image_raw': {'type': 'sensor_msgs/msg/Image', 'count': 6}}
    assert info['duration_s'] == 2.5 and info['message_count'] == 6
    # a single .mcap file works too
    mcap_file = next(out.glob('*.mcap'))
    assert bag.bag_info(mcap_file)['message_count'] == 6


def test_write_bag_any_message_type(tmp_path):
    """write_bag takes any rclpy messages: an image topic and a landmarks cloud topic together."""
    from lln_ros.core.landmarks import LandmarkSet, l2_normalize

    rng = np.random.default_rng(0)
    cells = np.array([[3, 2], [0, 0], [11, 8]], np.int32)
    cell_size = np.array([512 / 12, 384 / 9], np.float32)
    lset = LandmarkSet(
        l2_normalize(rng.random(8)).astype(np.float32),
        l2_normalize(rng.random((3, 8))).astype(np.float32),
        cells,
        ((cells + 0.5) * cell_size).astype(np.float32),
        np.array([3, 2, 1], np.float32),
        cell_size,
        np.array([512, 384], np.float32),
        (9, 12),
    ).validate()
    image = msgs.array_to_image(np.zeros((48, 64, 3), np.uint8), 'rgb8', msgs.make_header(10, 'camera'))
    cloud = msgs.landmarks_to_cloud(lset, msgs.make_header(10, 'camera'))
    out = tmp_path / 'bag'
    assert (
        bag.write_bag(
            out, [('/camera/image_raw', image, 10), ('/lln/landmarks', cloud, 10), ('/camera/image_raw', image, 20)]
        )
        == 3
    )
    info = bag.bag_info(out)
    assert info['topics']['/lln/landmarks'] == {'type': 'sensor_msgs/msg/PointCloud2', 'count': 1}
    ((_, back, _),) = bag.read_messages(out, topics=['/lln/landmarks'])
    np.testing.assert_array_equal(msgs.cloud_to_landmarks(back).descriptors, lset.descriptors)


@pytest.mark.skipif(not RTABMAP.is_dir(), reason=f'real data not available: {RTABMAP} is absent')
@pytest.mark.parametrize('compressed', [False, True])
def test_from_images_rtabmap_loop(tmp_path, compressed, capsys):
    out = tmp_path / 'rtabmap'
    # no --glob: the ground-truth bitmap samples_GT.bmp beside the .jpg frames is skipped and said so
    args = ['from-images', RTABMAP, out, '--fps', 2] + (['--compressed'] if compressed else [])
    assert cli(*args) == 0
    captured = capsys.readouterr()
    assert 'wrote 84 images' in captured.out
    assert '84 frames; skipped' in captured.err and 'samples_GT.bmp' in captured.err
    got = list(bag.read_messages(out))
    assert len(got) == 84
    for i, (_, msg, stamp) in enumerate(got):
        assert stamp == bag.DEFAULT_START_NS + i * 500_000_000
        array, order = msgs.message_to_array(msg)
        assert array.shape == (384, 512, 3)
        if i in (0, 9, 10, 83):  # natural order: frame i is file i+1.jpg
            want = cv2.imread(str(RTABMAP / f'{i + 1}.jpg'))
            if order == 'rgb':
                np.testing.assert_array_equal(array, want[:, :, ::-1])
            else:
                assert np.abs(array.astype(int) - want.astype(int)).mean() < 4
    assert len(mcap_messages(out)) == 84


def test_from_images_skips_other_files_and_counts_them(tmp_path, capsys):
    make_images(tmp_path / 'imgs', 3, suffix='.jpg')
    cv2.imwrite(str(tmp_path / 'imgs' / 'gt.bmp'), np.zeros((8, 8), np.uint8))  # a ground-truth bitmap
    (tmp_path / 'imgs' / 'notes.txt').write_text('not an image')
    assert cli('from-images', tmp_path / 'imgs', tmp_path / 'bag') == 0
    out, err = capsys.readouterr()
    assert 'wrote 3 images' in out
    assert err.strip() == (
        f'lln-bag: {tmp_path / "imgs"}: 3 frames; skipped 2 files: 1 not an image (notes.txt), '
        '1 .bmp beside the .jpg frames (gt.bmp; --glob picks the frames explicitly)'
    )
    assert [msg.width for _, msg, _ in bag.read_messages(tmp_path / 'bag')] == [64] * 3  # gt.bmp is 8 wide
    # --glob names the frames: every match is one, other files are not reported as skipped kinds
    assert cli('from-images', tmp_path / 'imgs', tmp_path / 'bag2', '--glob', '*.bmp') == 0
    assert 'wrote 1 images' in capsys.readouterr().out
    paths, skipped = bag.frame_images(tmp_path / 'imgs')
    assert [p.name for p in paths] == ['1.jpg', '2.jpg', '3.jpg']
    assert skipped == {'not_image': ['notes.txt'], 'other_kind': ['gt.bmp'], 'kind': '.jpg'}


def test_from_images_a_clean_folder_says_nothing_on_stderr(tmp_path, capsys):
    make_images(tmp_path / 'imgs', 2)
    assert cli('from-images', tmp_path / 'imgs', tmp_path / 'bag') == 0
    assert capsys.readouterr().err == ''


def test_from_images_rate_is_the_old_name_of_fps(tmp_path, capsys):
    make_images(tmp_path / 'imgs', 3)
    assert cli('from-images', tmp_path / 'imgs', tmp_path / 'bag', '--rate', 2) == 0
    captured = capsys.readouterr()
    assert 'lln-bag from-images: note: --rate is deprecated here, use --fps' in captured.err
    assert '2 Hz' in captured.out
    stamps = [t for _, _, t in bag.read_messages(tmp_path / 'bag')]
    assert np.diff(stamps).tolist() == [500_000_000] * 2


def test_play_speed_and_its_ros2_spelling_are_one_option():
    from lln_ros.cli.bag import build_parser

    for flag in ('--speed', '-r', '--rate'):
        assert build_parser().parse_args(['play', 'b', flag, '3']).speed == 3.0
    assert build_parser().parse_args(['play', 'b']).speed == 1.0
    assert build_parser().parse_args(['from-images', 'd', 'o']).fps == 10.0


def test_a_directory_given_as_an_image_says_so(tmp_path):
    from lln_ros.io.image import load_image

    (tmp_path / 'frames.png').mkdir()
    with pytest.raises(ImageError, match='is a directory, not an image file'):
        bag.write_image_bag([tmp_path / 'frames.png'], tmp_path / 'b')
    with pytest.raises(ImageError, match='is a directory, not an image file'):
        load_image(str(tmp_path / 'frames.png'))
    with pytest.raises(ImageError, match='image file not found'):
        load_image(str(tmp_path / 'missing.png'))


# ---------------------------------------------------------------- errors


def assert_cli_error(capsys, args, match):
    assert cli(*args) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('lln-bag: error: ') and match in err and '\n' not in err, err


def test_from_images_errors(tmp_path, capsys):
    assert_cli_error(capsys, ['from-images', tmp_path / 'missing', tmp_path / 'b1'], 'does not exist')
    (tmp_path / 'empty').mkdir()
    (tmp_path / 'empty' / 'readme.txt').write_text('x')
    assert_cli_error(capsys, ['from-images', tmp_path / 'empty', tmp_path / 'b2'], 'holds no images')
    assert_cli_error(
        capsys, ['from-images', tmp_path / 'empty', tmp_path / 'b2', '--glob', '*.jpg'], "no images matching '*.jpg'"
    )
    make_images(tmp_path / 'bad', 4)
    (tmp_path / 'bad' / '3.png').write_bytes(b'this is not a png')
    assert_cli_error(capsys, ['from-images', tmp_path / 'bad', tmp_path / 'b3'], 'cannot decode image')
    assert not (tmp_path / 'b3').exists()  # the partial bag is removed
    make_images(tmp_path / 'good', 2)
    (tmp_path / 'b4').mkdir()
    assert_cli_error(capsys, ['from-images', tmp_path / 'good', tmp_path / 'b4'], 'already exists')
    with pytest.raises(ImageError):
        bag.write_image_bag([tmp_path / 'bad' / '3.png'], tmp_path / 'b5')
    with pytest.raises(SystemExit):  # argparse: fps must be positive
        cli('from-images', tmp_path / 'good', tmp_path / 'b6', '--fps', 0)


def test_bag_errors(tmp_path, capsys):
    assert_cli_error(capsys, ['info', tmp_path / 'nope'], 'does not exist')
    (tmp_path / 'notabag').mkdir()
    assert_cli_error(capsys, ['info', tmp_path / 'notabag'], 'cannot open bag')
    make_images(tmp_path / 'imgs', 3)
    good = tmp_path / 'good'
    bag.folder_to_bag(tmp_path / 'imgs', good)
    corrupt = tmp_path / 'corrupt'
    corrupt.mkdir()
    (corrupt / 'metadata.yaml').write_text((good / 'metadata.yaml').read_text())
    mcap_file = next(good.glob('*.mcap'))
    (corrupt / mcap_file.name).write_bytes(mcap_file.read_bytes()[: len(mcap_file.read_bytes()) // 2])
    assert_cli_error(capsys, ['info', corrupt], 'cannot open bag')
    assert_cli_error(capsys, ['play', corrupt], 'cannot open bag')
    assert_cli_error(capsys, ['play', tmp_path / 'nope'], 'does not exist')
    assert_cli_error(capsys, ['play', good, '--topic-remap', 'nonsense'], 'must look like')
    assert_cli_error(capsys, ['play', good, '--topics', '/other'], 'not in the bag')


# ---------------------------------------------------------------- play

SUBSCRIBER = r"""
import hashlib, json, sys, time
import rclpy
from rclpy.qos import QoSProfile, ReliabilityPolicy
from lln_ros.ros.bag import message_class
topic, msgtype, reliability = sys.argv[1], sys.argv[2], sys.argv[5]
expected, timeout = int(sys.argv[3]), float(sys.argv[4])
rclpy.init()
node = rclpy.create_node('test_bag_subscriber')
got = []
def callback(msg, info):
    # 'sent': when the player wrote it (the DDS source timestamp), which a loaded machine's late
    # spin cannot compress; 't': when we took it, for the idle timeout below
    got.append({'t': time.monotonic(), 'sent': info['source_timestamp'] * 1e-9,
                'stamp': [msg.header.stamp.sec, msg.header.stamp.nanosec],
                'frame_id': msg.header.frame_id, 'sha1': hashlib.sha1(bytes(msg.data)).hexdigest(),
                'size': [getattr(msg, 'width', 0), getattr(msg, 'height', 0)]})
qos = QoSProfile(depth=100, reliability=getattr(ReliabilityPolicy, reliability.upper()))
node.create_subscription(message_class(msgtype), topic, callback, qos)
print('READY', flush=True)
deadline = time.monotonic() + timeout
while len(got) < expected and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.05)
    if got and time.monotonic() - got[-1]['t'] > 5.0:
        break  # idle after the last message: the rest is not coming (best effort may drop)
print(json.dumps(got), flush=True)
node.destroy_node()
rclpy.shutdown()
"""


def run_play(tmp_path, bag_dir, topic, msgtype, expected, play_args, reliability='reliable', timeout=30.0):
    """Start a subscriber process, then `lln-bag play` in another; return what the subscriber got."""
    env = ros_env(tmp_path)
    sub = subprocess.Popen(
        [PY, '-c', SUBSCRIBER, topic, msgtype, str(expected), str(timeout), reliability],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert sub.stdout.readline().strip() == 'READY', sub.stderr.read()
        play = subprocess.run(
            [
                PY,
                '-m',
                'lln_ros.cli.bag',
                'play',
                str(bag_dir),
                '--wait-subscribers',
                '1',
                '--wait-timeout',
                '20',
                *map(str, play_args),
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=timeout + 30,
        )
        assert play.returncode == 0, play.stderr
        out, err = sub.communicate(timeout=timeout + 10)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.communicate()
    assert sub.returncode == 0, err
    return json.loads(out.strip().splitlines()[-1]), play.stdout


def expected_messages(bag_dir):
    return [
        {
            'stamp': [msg.header.stamp.sec, msg.header.stamp.nanosec],
            'frame_id': msg.header.frame_id,
            'sha1': hashlib.sha1(bytes(msg.data)).hexdigest(),
        }
        for _, msg, _ in bag.read_messages(bag_dir)
    ]


def test_play_into_subscriber_in_order(tmp_path):
    make_images(tmp_path / 'imgs', 10, size=(160, 120))
    out = tmp_path / 'bag'
    bag.folder_to_bag(tmp_path / 'imgs', out, rate=2.0)  # 4.5 s of recording
    want = expected_messages(out)
    t0 = time.monotonic()
    got, log = run_play(
        tmp_path,
        out,
        '/replayed/image',
        'sensor_msgs/msg/Image',
        10,
        ['--speed', 10, '--topic-remap', '/camera/image_raw:=/replayed/image'],
    )
    assert time.monotonic() - t0 < 60
    assert [{k: g[k] for k in ('stamp', 'frame_id', 'sha1')} for g in got] == want
    assert all(g['size'] == [160, 120] for g in got)
    span = got[-1]['sent'] - got[0]['sent']
    assert span >= 4.5 / 10 * 0.8, span  # recorded timing divided by the speed, never faster
    assert span < 4.5 / 2, span  # and clearly faster than real time
    assert 'published 10 messages' in log


def test_play_compressed_best_effort(tmp_path):
    make_images(tmp_path / 'imgs', 5, suffix='.jpg')
    out = tmp_path / 'bag'
    bag.folder_to_bag(tmp_path / 'imgs', out, rate=20.0, compressed=True, topic='/cam/compressed')
    want = expected_messages(out)
    got, _ = run_play(
        tmp_path,
        out,
        '/cam/compressed',
        'sensor_msgs/msg/CompressedImage',
        5,
        ['--qos', 'best_effort', '--start-delay', '0.5'],
        reliability='best_effort',
    )
    # best effort may drop on a busy machine; what arrives is in order and intact
    got = [{k: g[k] for k in ('stamp', 'frame_id', 'sha1')} for g in got]
    assert got and all(g in want for g in got)
    assert [want.index(g) for g in got] == sorted(want.index(g) for g in got)


def test_play_times_out_without_subscribers(tmp_path):
    make_images(tmp_path / 'imgs', 2)
    out = tmp_path / 'bag'
    bag.folder_to_bag(tmp_path / 'imgs', out)
    play = subprocess.run(
        [PY, '-m', 'lln_ros.cli.bag', 'play', str(out), '--wait-subscribers', '1', '--wait-timeout', '0.5'],
        env=ros_env(tmp_path),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert play.returncode == 2
    assert 'timed out after 0.5 s waiting for 1 subscriber' in play.stderr


SIM_TIME_SUBSCRIBER = r"""
import json, sys, time
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image
expected, timeout = int(sys.argv[1]), float(sys.argv[2])
rclpy.init()
node = rclpy.create_node('test_sim_time', parameter_overrides=[Parameter('use_sim_time', value=True)])
got, clocks = [], []
def on_image(msg):
    now = node.get_clock().now().nanoseconds
    got.append({'stamp': msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec, 'now': now,
                'wall': time.monotonic()})
node.create_subscription(
    Image, '/camera/image_raw', on_image, QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
)
node.create_subscription(Clock, '/clock', lambda m: clocks.append(m.clock.sec * 10**9 + m.clock.nanosec),
                         QoSProfile(depth=10, reliability=ReliabilityPolicy.BEST_EFFORT))
print('READY', flush=True)
deadline = time.monotonic() + timeout
while len(got) < expected and time.monotonic() < deadline:
    rclpy.spin_once(node, timeout_sec=0.02)
print(json.dumps({'got': got, 'clocks': clocks}), flush=True)
node.destroy_node()
rclpy.shutdown()
"""


def test_play_clock_drives_sim_time_faster_than_real_time(tmp_path):
    """--clock publishes the bag time on /clock; a node with use_sim_time=true then reads every
    message's stamp as (about) the present, though the 4.5 s bag plays at 5x, faster than real time.
    While playback waits, /clock already holds the bag's start time."""
    make_images(tmp_path / 'imgs', 10, size=(160, 120))
    out = tmp_path / 'bag'
    stamps = bag.folder_to_bag(tmp_path / 'imgs', out, rate=2.0)
    env = ros_env(tmp_path)
    sub = subprocess.Popen(
        [PY, '-c', SIM_TIME_SUBSCRIBER, '10', '40'], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert sub.stdout.readline().strip() == 'READY', sub.stderr.read()
        play = subprocess.run(
            [
                PY,
                '-m',
                'lln_ros.cli.bag',
                'play',
                str(out),
                '--wait-subscribers',
                '1',
                '--wait-timeout',
                '20',
                '--rate',
                '5',
                '--clock',
                '50',
                '--start-delay',
                '1',
            ],
            env=env,
            capture_output=True,
            text=True,
            timeout=90,
        )
        assert play.returncode == 0, play.stderr
        assert 'bag time on /clock at 50 Hz' in play.stdout, play.stdout
        result, err = sub.communicate(timeout=60)
    finally:
        if sub.poll() is None:
            sub.kill()
            sub.communicate()
    assert sub.returncode == 0, err
    result = json.loads(result.strip().splitlines()[-1])
    got, clocks = result['got'], result['clocks']
    assert [g['stamp'] for g in got] == stamps  # reliable: every frame, in order, stamps unchanged
    assert clocks == sorted(clocks), 'the clock ran backwards'
    # while playback waits (--start-delay 1 s at 50 Hz), /clock holds the bag's start: a node has the
    # bag's time before the first message, never judges it by time 0
    assert clocks.count(stamps[0]) >= 10, clocks[:60]
    # the bag's span, never beyond it; the subscriber stops at the last image, and /clock (best effort, another
    # topic) may still be on its way, so the last clock seen is within a few ticks of the last stamp
    assert stamps[0] <= clocks[0] and clocks[-1] <= stamps[-1] and stamps[-1] - clocks[-1] < 0.5e9, (clocks, stamps)
    ages = [(g['now'] - g['stamp']) / 1e9 for g in got]
    span = (stamps[-1] - stamps[0]) / 1e9
    # the clock reaches a stamp before its message goes out (at 50 Hz x rate 5 it advances 0.1 s a
    # tick), so a node reads each stamp as about the present. On a loaded machine one image can wait
    # in the subscriber's queue while /clock moves on (seen: 1.0 s of bag time = 0.2 s of wall time),
    # so single ages may be late, never beyond the bag, and at most one best-effort tick early
    assert all(-0.2 <= a <= span for a in ages), ages
    assert 0 <= float(np.median(ages)) < 0.5, ages
    wall = got[-1]['wall'] - got[0]['wall']
    assert wall < span, f'{wall:.2f} s of wall time for {span:.1f} s of bag at rate 5'


TEARDOWN_STUCK = """
import threading, time
from lln_ros.ros.dds import exit_if_teardown_hangs
print('published', flush=True)
exit_if_teardown_hangs('lln-bag', 0.5, done='all 3 messages were published')
threading.Event().wait()  # a teardown that never returns, as the Fast DDS deadlock does
"""


def test_a_stuck_teardown_ends_the_player_with_its_status():
    """The player arms this watchdog once every message is out: a process whose only work left is a
    deadlocked DDS teardown exits 0 with a warning instead of hanging whoever waits on it."""
    t0 = time.monotonic()
    done = subprocess.run([PY, '-c', TEARDOWN_STUCK], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout == 'published\n'
    assert 'DDS teardown did not finish within 0.5 s; exiting (all 3 messages were published)' in done.stderr
    assert time.monotonic() - t0 < 50
