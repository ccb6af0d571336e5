"""lln-bag: make, inspect and play MCAP bags on machines without rosbag2.

lln-bag from-images DIR OUT [--glob '*.jpg'] [--topic /camera/image_raw] [--fps HZ]
                            [--compressed] [--frame-id camera] [--start SEC]
lln-bag info BAG [--json]
lln-bag play BAG [--speed X] [--topic-remap A:=B ...] [--qos reliable|best_effort]
                 [--wait-subscribers N --wait-timeout S] [--clock [HZ]]
                 [--pace TOPIC [--pace-timeout S]]

Two quantities, two names: --fps is frames per second (the stamps from-images writes), --speed a
factor on the recorded timing (play; -r/--rate is ros2 bag play's spelling of it and is accepted).
from-images --rate, its old name, still works with a deprecation note.

from-images takes the image files of DIR (by suffix); when they are of several kinds, the most
common one is the frames (rtabmap_loop/ holds samples_GT.bmp beside its .jpg frames); what is
skipped is counted on stderr. --glob picks the frames explicitly.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..ros.dds import exit_if_teardown_hangs
from .common import run_cli

# a player's work is over when every message is acknowledged; a teardown longer than this is the
# Fast DDS participant-deletion deadlock (exit_if_teardown_hangs), not work
TEARDOWN_TIMEOUT_S = 10.0


class DeprecatedAlias(argparse.Action):
    """An old option spelling: stores into the new option's dest and says so on stderr."""

    def __init__(self, option_strings, dest, new: str = '', **kwargs):
        self.new = new
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f'{parser.prog}: note: {option_string} is deprecated here, use {self.new}', file=sys.stderr)
        setattr(namespace, self.dest, values)


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f'must be positive, got {text}')
    return value


def build_parser() -> argparse.ArgumentParser:
    from ..ros.bag import DEFAULT_START_NS, DEFAULT_TOPIC

    p = argparse.ArgumentParser(prog='lln-bag', description=__doc__.strip().splitlines()[0])
    sub = p.add_subparsers(dest='command', required=True, metavar='COMMAND')

    f = sub.add_parser(
        'from-images',
        help='write an ordered image folder as an MCAP bag',
        description='Write the images of DIR (natural sort: 2.jpg before 10.jpg) as one '
        'image topic of a new MCAP bag OUT, stamped at a fixed rate.',
    )
    f.add_argument('folder', metavar='DIR')
    f.add_argument('out', metavar='OUT', help='bag directory to create (must not exist)')
    f.add_argument(
        '--glob',
        metavar='PATTERN',
        help="only the files of DIR matching PATTERN, e.g. '*.jpg' (default: the image files of its most "
        'common kind; the others are skipped and counted on stderr)',
    )
    f.add_argument('--topic', default=DEFAULT_TOPIC, help=f'image topic (default {DEFAULT_TOPIC})')
    f.add_argument('--fps', type=_positive, default=10.0, metavar='HZ', help='frames per second (default 10)')
    f.add_argument('--rate', dest='fps', type=_positive, action=DeprecatedAlias, new='--fps', help='deprecated: --fps')
    f.add_argument(
        '--compressed', action='store_true', help='sensor_msgs/CompressedImage jpeg instead of sensor_msgs/Image rgb8'
    )
    f.add_argument('--frame-id', default='camera', help='header frame_id (default camera)')
    f.add_argument(
        '--start',
        type=float,
        default=DEFAULT_START_NS / 1e9,
        help=f'stamp of the first frame, seconds since the epoch (default {DEFAULT_START_NS // 10**9})',
    )
    f.add_argument('--jpeg-quality', type=int, default=95, help='with --compressed (default 95)')

    i = sub.add_parser('info', help='topics, types, counts and duration of a bag')
    i.add_argument('bag', metavar='BAG')
    i.add_argument('--json', action='store_true', help='print one JSON object')

    pl = sub.add_parser(
        'play',
        help='publish a bag into the ROS graph with rclpy',
        description='Publish the recorded messages (raw CDR) at the recorded timing divided by --speed.',
    )
    pl.add_argument('bag', metavar='BAG')
    pl.add_argument(
        '--speed',
        '-r',
        '--rate',
        type=_positive,
        default=1.0,
        metavar='X',
        help='speed factor on the recorded timing, 2 = twice as fast (default 1; -r/--rate as in ros2 bag play)',
    )
    pl.add_argument(
        '--topic-remap', action='append', default=[], metavar='A:=B', help='publish bag topic A on B (repeatable)'
    )
    pl.add_argument(
        '--topics',
        type=lambda text: [t for t in text.split(',') if t],
        metavar='T1,T2',
        help='play only these bag topics (comma-separated; default: all)',
    )
    pl.add_argument('--qos', choices=['reliable', 'best_effort'], default='reliable')
    pl.add_argument('--qos-depth', type=int, default=100, help='publisher history depth (default 100)')
    pl.add_argument(
        '--wait-subscribers',
        type=int,
        default=0,
        metavar='N',
        help='start only when every played topic has N subscribers (default 0: start now)',
    )
    pl.add_argument(
        '--wait-timeout',
        type=_positive,
        default=10.0,
        metavar='S',
        help='give up waiting for subscribers after S seconds (default 10)',
    )
    pl.add_argument(
        '--start-delay',
        type=float,
        default=0.0,
        metavar='S',
        help='sleep S seconds after the subscribers are there (default 0)',
    )
    pl.add_argument(
        '--clock',
        type=_positive,
        nargs='?',
        const=40.0,
        default=0.0,
        metavar='HZ',
        help='publish the bag time on /clock (rosgraph_msgs/Clock) at HZ (default 40 when '
        'given), for nodes started with -p use_sim_time:=true (as ros2 bag play --clock); while '
        "playback waits (--wait-subscribers, --start-delay) it holds the bag's start time",
    )
    pl.add_argument(
        '--pace',
        metavar='TOPIC',
        default='',
        help='lossless replay into a slower node: after each message wait for one message on '
        "TOPIC (e.g. the extractor's lln/landmarks), at most --pace-timeout s; the recorded "
        'timing stays the fastest pace',
    )
    pl.add_argument(
        '--pace-timeout',
        type=_positive,
        default=10.0,
        metavar='S',
        help='with --pace: give up waiting for one output after S seconds and go on (default 10)',
    )
    pl.add_argument('--quiet', action='store_true', help='print nothing but errors')
    return p


def skipped_note(skipped: dict, shown: int = 3) -> str:
    """'2 files: 1 not an image (notes.txt), 1 .bmp beside the .jpg frames (samples_GT.bmp; --glob
    picks other frames)' or '' when nothing was skipped."""

    def names(items):
        return ', '.join(items[:shown]) + (', ...' if len(items) > shown else '')

    parts = []
    if skipped['not_image']:
        n = len(skipped['not_image'])
        parts.append(f'{n} not {"an image" if n == 1 else "images"} ({names(skipped["not_image"])})')
    if skipped['other_kind']:
        kinds = sorted({Path(n).suffix.lower() for n in skipped['other_kind']})
        parts.append(
            f'{len(skipped["other_kind"])} {"/".join(kinds)} beside the {skipped["kind"]} frames '
            f'({names(skipped["other_kind"])}; --glob picks the frames explicitly)'
        )
    total = len(skipped['not_image']) + len(skipped['other_kind'])
    return f'{total} file{"s" if total != 1 else ""}: ' + ', '.join(parts) if parts else ''


def run(args) -> int:
    from ..ros import bag

    if args.command == 'from-images':
        paths, skipped = bag.frame_images(args.folder, args.glob)
        note = skipped_note(skipped)
        if note:
            print(f'lln-bag: {args.folder}: {len(paths)} frames; skipped {note}', file=sys.stderr)
        stamps = bag.write_image_bag(
            paths,
            args.out,
            topic=args.topic,
            rate=args.fps,
            compressed=args.compressed,
            frame_id=args.frame_id,
            start_ns=int(round(args.start * 1e9)),
            jpeg_quality=args.jpeg_quality,
        )
        kind = 'sensor_msgs/msg/CompressedImage jpeg' if args.compressed else 'sensor_msgs/msg/Image rgb8'
        print(
            f'wrote {len(stamps)} images to {args.out} on {args.topic} ({kind}, {args.fps:g} Hz, '
            f'{(stamps[-1] - stamps[0]) / 1e9:.3f} s)'
        )
    elif args.command == 'info':
        info = bag.bag_info(args.bag)
        print(json.dumps(info) if args.json else bag.format_info(info))
    elif args.command == 'play':
        from ..ros import player
        from ..ros.dds import apply_large_data_profile

        log = (lambda _m: None) if args.quiet else (lambda m: print(f'lln-bag: {m}', flush=True))
        level, note = apply_large_data_profile()  # a player publishes camera-sized frames: before rclpy.init
        if level == 'warn':
            print(f'lln-bag: warning: {note}', file=sys.stderr)
        else:
            log(note)
        player.play_bag(
            args.bag,
            rate=args.speed,
            remaps=player.parse_remaps(args.topic_remap),
            qos=args.qos,
            qos_depth=args.qos_depth,
            wait_subscribers=args.wait_subscribers,
            wait_timeout=args.wait_timeout,
            topics=args.topics,
            start_delay=args.start_delay,
            log=log,
            clock_hz=args.clock,
            pace_topic=args.pace,
            pace_timeout=args.pace_timeout,
            on_published=lambda n: exit_if_teardown_hangs(
                'lln-bag', TEARDOWN_TIMEOUT_S, done=f'all {n} messages were published'
            ),
        )
    return 0


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    return run_cli('lln-bag', lambda: run(args))


if __name__ == '__main__':
    sys.exit(main())
