"""lln_ros.ros.stream: missing frames from stamp gaps, and counter windows (no rclpy)."""

from lln_ros.ros.stream import StampGaps, Window

MS = 1_000_000


def test_gaps_count_missing_frames_at_the_learnt_rate():
    gaps = StampGaps(warmup=5)
    t = 0
    for _ in range(10):  # 30 Hz, steady
        assert gaps.add(t) == 0
        t += 33 * MS
    t += 3 * 33 * MS  # three frames lost: the next one is 4 periods later
    assert gaps.add(t) == 3
    assert gaps.add(t + 33 * MS) == 0 and gaps.missing == 3
    assert gaps.add(t) == 0 and gaps.out_of_order == 1  # repeated / older stamps are not gaps


def test_gaps_follow_a_rate_change_and_ignore_jitter():
    gaps = StampGaps(window=10, warmup=5)
    t = 0
    for i in range(20):  # 10 Hz with +-20% jitter: never a gap
        t += (100 + (20 if i % 2 else -20)) * MS
        assert gaps.add(t) == 0
    for _ in range(30):  # the camera drops to 5 Hz: counted as losses until the median learns it
        t += 200 * MS
        gaps.add(t)
    assert gaps.missing <= 10 // 2 + 1
    before = gaps.missing
    for _ in range(10):
        t += 200 * MS
        assert gaps.add(t) == 0  # learnt: 200 ms is the new period
    assert gaps.missing == before


def test_no_period_before_warmup():
    gaps = StampGaps(warmup=5)
    assert gaps.add(0) == 0 and gaps.add(1000 * MS) == 0 and gaps.period_ns() is None


def test_window_deltas():
    counts = {'a': 1}
    w = Window(lambda: counts)
    counts = {'a': 4, 'b': 2}
    assert w.delta() == {'a': 3, 'b': 2}
    assert w.delta() == {}


def test_pauses_and_restarts_are_not_losses():
    gaps = StampGaps(warmup=5)
    t = 0
    for _ in range(10):
        gaps.add(t)
        t += 100 * MS
    assert gaps.add(t + 3600 * 10**9) == 0  # an hour later: a pause, not 36000 lost frames
    assert gaps.add(0) == 0 and gaps.out_of_order == 1  # the bag again from the start
    assert gaps.add(100 * MS) == 0 and gaps.add(400 * MS) == 2 and gaps.missing == 2
