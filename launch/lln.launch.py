"""Both lln_ros nodes with the packaged configs (for real ROS 2 installs: `ros2 launch`).

    ros2 launch lln_ros lln.launch.py image:=/camera/image_raw mode:=mapping
    ros2 launch lln_ros lln.launch.py image:=/camera/image_raw image_transport:=compressed \
        map_path:=~/maps/campus.db mode:=localization
    ros2 launch lln_ros lln.launch.py feed:=keyframes map_path:=/tmp/reference.db   # build a map only

The extractor subscribes `image` (or `image/compressed`), both remapped from the `image` argument;
its `landmarks` go to the matcher's `query` (answered; in mapping mode also stored) or, with
feed:=keyframes, to `keyframes` (stored, not answered). Parameters come from the YAML files in
share/lln_ros/config, then the launch arguments below override theirs. See docs/interfaces.md.
"""
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    config = PathJoinSubstitution([FindPackageShare('lln_ros'), 'config'])
    image = LaunchConfiguration('image')
    arguments = [
        DeclareLaunchArgument('image', default_value='/camera/image_raw',
                              description='camera image topic (sensor_msgs/Image); with image_transport '
                                          'compressed, <image>/compressed is used'),
        DeclareLaunchArgument('image_transport', default_value='raw', choices=['raw', 'compressed'],
                              description='raw: sensor_msgs/Image | compressed: sensor_msgs/CompressedImage'),
        DeclareLaunchArgument('reliability', default_value='best_effort', choices=['best_effort', 'reliable'],
                              description='image subscription QoS: best_effort (camera drivers) | '
                                          'reliable (bag playback without drops)'),
        DeclareLaunchArgument('mode', default_value='localization', choices=['localization', 'mapping'],
                              description='localization: answer queries, map unchanged | mapping: answer '
                                          'each query, then store it (online loop-closure detection)'),
        DeclareLaunchArgument('feed', default_value='query', choices=['query', 'keyframes'],
                              description="matcher input fed by the extractor's landmarks"),
        DeclareLaunchArgument('map_path', default_value='~/.ros/lln_ros/map.db',
                              description='SQLite map file (created if missing)'),
        DeclareLaunchArgument('extractor_params', default_value=PathJoinSubstitution([config, 'extractor.yaml']),
                              description='parameter file of the extractor'),
        DeclareLaunchArgument('matcher_params', default_value=PathJoinSubstitution([config, 'matcher.yaml']),
                              description='parameter file of the matcher'),
    ]
    extractor = Node(
        package='lln_ros', executable='extractor', name='lln_extractor', output='screen', emulate_tty=True,
        parameters=[LaunchConfiguration('extractor_params'),
                    {'image_transport': LaunchConfiguration('image_transport'),
                     'reliability': LaunchConfiguration('reliability')}],
        remappings=[('image', image), ('image/compressed', [image, '/compressed'])],
    )
    matcher = Node(
        package='lln_ros', executable='matcher', name='lln_matcher', output='screen', emulate_tty=True,
        parameters=[LaunchConfiguration('matcher_params'),
                    {'mode': LaunchConfiguration('mode'), 'map_path': LaunchConfiguration('map_path')}],
        remappings=[(LaunchConfiguration('feed'), 'landmarks')],
    )
    return LaunchDescription(arguments + [extractor, matcher])
