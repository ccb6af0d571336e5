"""ROS glue shared by the lln_ros nodes (parameters: nodes/parameters.py): QoS, counters and diagnostics
(levels: WARN for losses and refused input, ERROR when all input is refused)."""

from __future__ import annotations

import functools
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

from ..core.counters import Counters, problem_kind

RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}

# the extractor's model_info: latched so a matcher started later still learns the model
MODEL_QOS = QoSProfile(
    depth=1,
    history=HistoryPolicy.KEEP_LAST,
    reliability=ReliabilityPolicy.RELIABLE,
    durability=DurabilityPolicy.TRANSIENT_LOCAL,
)


def subscription_qos(reliability: str, depth: int) -> QoSProfile:
    if reliability not in RELIABILITY:
        raise ValueError(f"reliability must be 'reliable' or 'best_effort', got {reliability!r}")
    if reliability == 'best_effort':
        return QoSProfile(
            depth=depth,
            history=qos_profile_sensor_data.history,
            reliability=ReliabilityPolicy.BEST_EFFORT,
            durability=qos_profile_sensor_data.durability,
        )
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


class Health(Counters):
    """A node's counters (lln_ros.core.counters: problems logged by kind, rate-limited) plus /diagnostics."""

    def __init__(self, node: Node):
        super().__init__(log=node.get_logger().warning)
        self.node = node

    def diagnostics(
        self, extra: dict | None = None, level: int = DiagnosticStatus.OK, message: str = 'running'
    ) -> DiagnosticArray:
        values = {**self.snapshot(), **(extra or {})}
        status = DiagnosticStatus(
            level=level,
            name=self.node.get_fully_qualified_name(),
            message=message,
            hardware_id='lln_ros',
            values=[KeyValue(key=k, value=str(v)) for k, v in sorted(values.items())],
        )
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        return msg


def guarded(what: str, fallback=None):
    """The one guard of every callback and publish path of a node (subscriptions, timers, services,
    the extractor's worker): an exception that escapes the body is counted as internal_error, logged
    by kind (the first time, then at most once a minute: Counters.problem), and swallowed, so no
    message, timer tick or service call ever ends the process. Refused input is the body's to count
    (bad_*); what reaches this guard is a fault of this code, by definition.

    A method decorator: the instance's `health` (a Health) counts. fallback(self, *args) -> the
    value to return instead (a service's response with success False); None by default.

        @guarded('query callback')
        def on_query(self, msg): ...
    """

    def wrap(fn):
        @functools.wraps(fn)
        def inner(self, *args, **kwargs):
            try:
                return fn(self, *args, **kwargs)
            except Exception as e:  # noqa: BLE001  one message, tick or call never ends the node
                text = f'{what}: unexpected {type(e).__name__}: {e}'
                self.health.problem('internal_error', text[:500], kind=f'{what}: {type(e).__name__}')
                return fallback(self, *args, **kwargs) if fallback is not None else None

        return inner

    return wrap


def failed_response(self, request, response):
    """guarded()'s fallback for a std_srvs/Trigger service: success False, the reason said."""
    response.success = False
    response.message = 'internal error (counted as internal_error; see the node log)'
    return response


def run_node(make_node, name: str, args=None) -> int:
    """init / spin / shutdown. A node that cannot start (corrupt map, bad parameter, missing
    weights) logs one fatal line naming the problem and exits 1, without a traceback.
    SIGINT and SIGTERM end the spin (stop_on_signals; a callback that runs then finishes first).
    At the end the node's own state is released first (node.close(): the map closed, the worker
    joined); only then is the DDS teardown run, under a watchdog (lln_ros.ros.dds.exit_if_teardown_hangs)."""
    import faulthandler

    import rclpy
    from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
    from rclpy.signals import SignalHandlerOptions

    from ..errors import LLNError
    from ..ros.dds import apply_large_data_profile, exit_if_teardown_hangs

    # a crash in native code (DDS, FAISS, ONNX Runtime) prints every thread's Python stack to stderr,
    # so a node that exits -11 says where
    faulthandler.enable()
    dds_level, dds_note = apply_large_data_profile()  # before rclpy.init: Fast DDS reads it then
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = stop_on_signals()
    node, executor, status = None, None, 0
    try:
        node = make_node()
        if dds_level == 'warn':
            node.get_logger().warning(dds_note)
        else:
            node.get_logger().info(dds_note)
        # a node may ask for its own executor (the matcher: sensor callbacks beside the answers)
        executor = node.make_executor() if hasattr(node, 'make_executor') else SingleThreadedExecutor()
        spin_until(executor, node, stop)
    except ExternalShutdownException:  # the context was shut down elsewhere (signals: stop_on_signals)
        pass
    except (LLNError, ValueError, OSError) as e:
        rclpy.logging.get_logger(name).fatal(f'cannot start: {e}')
        status = 1
    finally:
        if executor is not None:
            join_executor(executor, TEARDOWN_TIMEOUT_S)
        if node is not None and hasattr(node, 'close'):
            node.close()
        exit_if_teardown_hangs(name, TEARDOWN_TIMEOUT_S, status, done='its state was saved')
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return status


# how soon the spin notices SIGINT / SIGTERM when no message wakes it (Python runs a signal's handler
# only when the main thread is back in Python, not while rcl_wait blocks)
SIGNAL_POLL_S = 0.1


def stop_on_signals():
    """SIGINT and SIGTERM set the returned threading.Event, in place of rclpy's handlers (rclpy.init
    with SignalHandlerOptions.NO). Why not rclpy's: its handler raises KeyboardInterrupt in the main
    thread at once, while rclpy's signal thread still walks the list of every executor's SIGINT guard
    condition to trigger them; a teardown that destroys an executor frees that list and the guard
    condition under the walk: a segfault (CI: the matcher exited -11 at SIGINT, the main thread just
    past executor.shutdown; test/test_signal_teardown.py's node: 12 of 20 runs with rclpy's handler,
    0 of 20 with this one). Here no rclpy signal thread runs, and a callback that runs when the
    signal comes is not cut short."""
    import signal
    import threading

    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def spin_until(executor, node, stop) -> None:
    """rclpy.spin(node, executor) that also ends when `stop` (a threading.Event) is set."""
    executor.add_node(node)
    try:
        while not stop.is_set() and executor.context.ok():
            executor.spin_once(timeout_sec=SIGNAL_POLL_S)
    finally:
        executor.remove_node(node)


# a teardown longer than this is the Fast DDS participant-deletion deadlock, not work
TEARDOWN_TIMEOUT_S = 10.0


def join_executor(executor, timeout_s: float) -> bool:
    """Stop `executor` and wait (at most timeout_s) until no callback of it runs any more; False
    when one is still running then. The node's handles and state must outlive every callback:
    destroying a node while a worker thread takes from its subscription is a segfault (rclpy
    #255/#663; the matcher's -11 at SIGINT in CI had another cause: stop_on_signals). rclpy
    Jazzy's Executor.shutdown does not wait for a MultiThreadedExecutor's pool (its wait is skipped
    once _is_shutdown is set), so the pool, rclpy's ThreadPoolExecutor in `_executor`, is joined here."""
    import threading

    executor.shutdown(timeout_sec=timeout_s)
    pool = getattr(executor, '_executor', None)
    if pool is None:
        return True
    joiner = threading.Thread(target=pool.shutdown, kwargs={'wait': True}, daemon=True)
    joiner.start()
    joiner.join(timeout_s)
    return not joiner.is_alive()


def two_thread_executor():
    """rclpy's MultiThreadedExecutor (2 threads) with rclpy #1452 fixed as rclpy #1547 does (in
    Rolling 10.0.4; Jazzy's rclpy 7.1.6 has the bug): a callback already queued for the pool, not
    started yet, is yielded again and again by the wait loop, which resubmits it and spins instead
    of waiting. With use_sim_time, /clock at 40 Hz kept that loop busy and a matcher answered a bag
    replayed with --clock only after the bag had ended, every query stale (seen in CI:
    test_runtime.py::test_bag_replay_with_sim_time). Here a queued callback is submitted once."""
    import time

    from rclpy.executors import (
        ConditionReachedException,
        ExternalShutdownException,
        MultiThreadedExecutor,
        ShutdownException,
        TimeoutException,
    )

    class SubmitOnceExecutor(MultiThreadedExecutor):
        def __init__(self):
            super().__init__(num_threads=2)
            self.queued: list = []  # submitted callbacks not finished yet (rclpy's own list is private)

        def _spin_once_impl(self, timeout_sec=None, wait_condition=lambda: False) -> None:
            try:
                handler, _entity, _node = self.wait_for_ready_callbacks(timeout_sec, None, wait_condition)
            except (ExternalShutdownException, ShutdownException, TimeoutException, ConditionReachedException):
                return
            if any(handler is q for q in self.queued):
                time.sleep(0.001)  # it waits for a pool thread: let one take the GIL and start it
            else:
                self._executor.submit(handler)
                self.queued.append(handler)
            for task in [q for q in self.queued if q.done()]:
                self.queued.remove(task)
                task.result()  # a callback's exception ends spin, as rclpy's executor does

    return SubmitOnceExecutor()


LOG_PERIOD_S = 60.0  # a diagnostics problem of one kind is logged at most once a minute (as Counters does)


class Diagnostics:
    """Health counters on /diagnostics every `period` seconds (0 = off), with a level and message
    from status(delta) -> (level, message, log text) (see worst), where delta = the counters' increases since the last
    message (lln_ros.ros.stream.Window): WARN for losses and refused input of the last period, ERROR
    when the node refuses all input. The timer runs on the steady clock: with use_sim_time and a
    paused (or not yet started) bag, /clock stands still, and diagnostics must not."""

    def __init__(self, node: Node, health: Health, period: float, extra=lambda: {}, status=None):
        from rclpy.clock import Clock, ClockType

        from ..ros.stream import Window

        self.node, self.health, self.extra = node, health, extra
        self.status = status or (lambda delta: worst([]))
        self.window = Window(health.snapshot)
        self.pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
        self._clock = Clock(clock_type=ClockType.STEADY_TIME)
        self.timer = None
        self.logged: dict = {}
        self.set_period(period)

    def set_period(self, period: float) -> None:
        if self.timer is not None:
            self.node.destroy_timer(self.timer)
            self.timer = None
        if period > 0:
            self.timer = self.node.create_timer(period, self.publish, clock=self._clock)

    @guarded('diagnostics timer')
    def publish(self) -> None:
        try:
            level, message, log_text = self.status(self.window.delta())
        except Exception as e:  # noqa: BLE001  diagnostics must never take the node down
            self.health.problem('internal_error', f'diagnostics status: {type(e).__name__}: {e}')
            level, message, log_text = DiagnosticStatus.WARN, f'diagnostics status failed: {e}', ''
        # numbers masked: one line per kind of problem and minute, not one per period or count
        kind = (level, problem_kind(log_text))
        now = time.monotonic()
        if log_text and now - self.logged.get(kind, -1e9) >= LOG_PERIOD_S:
            self.logged[kind] = now
            # two call sites: rclpy refuses one call site logging at two severities
            if level == DiagnosticStatus.ERROR:
                self.node.get_logger().error(log_text)
            else:
                self.node.get_logger().warning(log_text)
        self.pub.publish(self.health.diagnostics(self.extra(), level, message))


def start_diagnostics(node: Node, health: Health, period: float, extra=lambda: {}, status=None) -> Diagnostics:
    """Publish health counters on /diagnostics every `period` seconds (0 = off); see Diagnostics."""
    return Diagnostics(node, health, period, extra, status)


def worst(problems: list[tuple]) -> tuple[int, str, str]:
    """(level, message, log text) of a diagnostics status from [(level, text[, quiet]), ...]: the
    worst level and every text joined; the log text leaves out the quiet ones (problems the node's
    counters log already, e.g. refused messages). OK 'running' when there are none."""
    if not problems:
        return DiagnosticStatus.OK, 'running', ''
    rank = lambda level: level[0] if isinstance(level, bytes) else int(level)  # noqa: E731  (levels are bytes)
    ordered = sorted(problems, key=lambda p: -rank(p[0]))
    return (
        ordered[0][0],
        '; '.join(p[1] for p in ordered),
        '; '.join(p[1] for p in ordered if not (len(p) > 2 and p[2])),
    )


def loss_events(health: Health, what: str):
    """rclpy event callbacks for a subscription: an incompatible QoS offer (nothing will arrive
    from that publisher) and DDS-reported lost samples are counted, so diagnostics can say so."""
    from rclpy.event_handler import SubscriptionEventCallbacks

    def incompatible(info) -> None:
        health.problem(
            'qos_incompatible',
            f'{what}: a publisher offers a QoS this subscription cannot match '
            f'(policy id {info.last_policy_kind}); nothing arrives from it',
        )

    def lost(info) -> None:
        health.count('dds_lost', int(info.total_count_change))

    return SubscriptionEventCallbacks(incompatible_qos=incompatible, message_lost=lost)
