"""ROS glue shared by the lln_ros nodes: parameter declaration, QoS, counters and diagnostics."""
from __future__ import annotations

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import (DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy,
                       qos_profile_sensor_data)

from ..counters import Counters

RELIABILITY = {'reliable': ReliabilityPolicy.RELIABLE, 'best_effort': ReliabilityPolicy.BEST_EFFORT}

# the extractor's model_info: latched so a matcher started later still learns the model
MODEL_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)


def declare(node: Node, spec: dict) -> dict:
    """Declare every parameter of `spec` {name: (default, description)} and return their values.
    Read-only: the nodes read them once at start, so `ros2 param set` says so instead of pretending."""
    values = {}
    for name, (default, description) in spec.items():
        node.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=True))
        values[name] = node.get_parameter(name).value
    return values


def subscription_qos(reliability: str, depth: int) -> QoSProfile:
    if reliability not in RELIABILITY:
        raise ValueError(f"reliability must be 'reliable' or 'best_effort', got {reliability!r}")
    if reliability == 'best_effort':
        return QoSProfile(depth=depth, history=qos_profile_sensor_data.history,
                          reliability=ReliabilityPolicy.BEST_EFFORT, durability=qos_profile_sensor_data.durability)
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)


class Health(Counters):
    """A node's counters (lln_ros.counters: problems logged by kind, rate-limited) plus /diagnostics."""

    def __init__(self, node: Node):
        super().__init__(log=node.get_logger().warning)
        self.node = node

    def diagnostics(self, extra: dict | None = None) -> DiagnosticArray:
        values = {**self.snapshot(), **(extra or {})}
        status = DiagnosticStatus(level=DiagnosticStatus.OK, name=self.node.get_fully_qualified_name(),
                                  message='running', hardware_id='lln_ros',
                                  values=[KeyValue(key=k, value=str(v)) for k, v in sorted(values.items())])
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        return msg


def run_node(make_node, name: str, args=None) -> int:
    """init / spin / shutdown. A node that cannot start (corrupt map, bad parameter, missing
    weights) logs one fatal line naming the problem and exits 1, without a traceback."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    from ..dds import apply_large_data_profile
    from ..errors import LLNError
    dds_level, dds_note = apply_large_data_profile()  # before rclpy.init: Fast DDS reads it then
    rclpy.init(args=args)
    node = None
    try:
        node = make_node()
        getattr(node.get_logger(), 'warning' if dds_level == 'warn' else 'info')(dds_note)
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (LLNError, ValueError, OSError) as e:
        rclpy.logging.get_logger(name).fatal(f'cannot start: {e}')
        return 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


def start_diagnostics(node: Node, health: Health, period: float, extra=lambda: {}) -> None:
    """Publish health counters on /diagnostics every `period` seconds (0 = off)."""
    if period <= 0:
        return
    pub = node.create_publisher(DiagnosticArray, '/diagnostics', 10)
    node.create_timer(period, lambda: pub.publish(health.diagnostics(extra())))
