"""Both lln_ros nodes with the packaged configs (for real ROS 2 installs: `ros2 launch`).

    ros2 launch lln_ros lln.launch.py image:=/camera/image_raw mode:=mapping
    ros2 launch lln_ros lln.launch.py image:=/camera/image_raw image_transport:=compressed \
        map_path:=~/maps/campus.db mode:=localization
    ros2 launch lln_ros lln.launch.py feed:=keyframes map_path:=/tmp/reference.db   # build a map only
    ros2 launch lln_ros lln.launch.py use_sim_time:=true reliability:=reliable frame_queue:=100  # bag, --clock
    ros2 launch lln_ros lln.launch.py namespace:=robot1 verify:=true visualize:=true rviz:=true \
        map_path:=milvus://127.0.0.1:19530?map=campus log_level:=debug
    ros2 launch lln_ros lln.launch.py image:=/camera/rgb/image_color verify:=true depth:=true \
        depth_image:=/camera/depth_registered/image_raw camera_info:=/camera/rgb/camera_info odom:=/odom  # metric

The extractor subscribes `image` (or `image/compressed`), both remapped from the `image` argument;
its `lln/landmarks` go to the matcher's `lln/query` (answered; in mapping mode also stored) or, with
feed:=keyframes, to `lln/keyframes` (stored, not answered). For metric answers (issue 27: T(keyframe <- query)
with a covariance, lln/pose in localization mode) the extractor takes the registered depth image (`depth_image`,
with depth:=true) and the matcher the colour camera's `camera_info` and the `odom` odometry, each remapped from
its argument. Every topic is relative (lln_ros.ros.topics),
so `namespace:=robot1` moves the whole pipeline, rviz included, under /robot1. Parameters come from the YAML files in
share/lln_ros/config, then the launch arguments below override theirs. Every process started here
(and any camera driver included after it in the same launch) gets the Fast DDS profile for
camera-sized images, unless FASTRTPS_DEFAULT_PROFILES_FILE is already set. See docs/interfaces.md.
"""

from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.conditions import IfCondition
from launch.substitutions import EnvironmentVariable, LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    share = FindPackageShare('lln_ros')
    config = PathJoinSubstitution([share, 'config'])
    image = LaunchConfiguration('image')
    namespace = LaunchConfiguration('namespace')
    use_sim_time = LaunchConfiguration('use_sim_time')
    verify = LaunchConfiguration('verify')
    camera_info, odom = LaunchConfiguration('camera_info'), LaunchConfiguration('odom')
    ros_arguments = ['--log-level', LaunchConfiguration('log_level')]
    arguments = [
        DeclareLaunchArgument(
            'image',
            default_value='camera/image_raw',
            description='camera image topic (sensor_msgs/Image; relative: inside the namespace); with '
            'image_transport compressed, <image>/compressed is used',
        ),
        DeclareLaunchArgument(
            'image_transport',
            default_value='raw',
            choices=['raw', 'compressed'],
            description='raw: sensor_msgs/Image | compressed: sensor_msgs/CompressedImage',
        ),
        DeclareLaunchArgument(
            'reliability',
            default_value='best_effort',
            choices=['best_effort', 'reliable'],
            description='image subscription QoS: best_effort (camera drivers) | reliable (bag playback without drops)',
        ),
        DeclareLaunchArgument(
            'frame_queue',
            default_value='1',
            description='frames waiting for extraction: 1 = newest only (cameras) | e.g. 100 '
            'for bag replays, so no frame is skipped',
        ),
        DeclareLaunchArgument(
            'mode',
            default_value='localization',
            choices=['localization', 'mapping'],
            description='localization: answer queries, map unchanged | mapping: answer '
            'each query, then store it (online loop-closure detection)',
        ),
        DeclareLaunchArgument(
            'feed',
            default_value='query',
            choices=['query', 'keyframes'],
            description="matcher input fed by the extractor's landmarks",
        ),
        DeclareLaunchArgument(
            'map_path',
            default_value='~/.ros/lln_ros/map.db',
            description='map URI: SQLite file path (created if missing) | '
            'milvus-lite:///path.db | milvus://host:port[/db][?map=name]',
        ),
        DeclareLaunchArgument(
            'verify',
            default_value='false',
            choices=['true', 'false'],
            description='re-rank candidates by keypoint inliers: the extractor publishes '
            'ORB keypoints, the matcher verifies and adds `inliers`',
        ),
        DeclareLaunchArgument(
            'depth',
            default_value='false',
            choices=['true', 'false'],
            description='the extractor subscribes depth_image and sends keypoint depths (with verify): PnP poses',
        ),
        DeclareLaunchArgument(
            'depth_image',
            default_value='camera/depth_registered/image_raw',
            description='depth image registered to the colour camera (REP 118: 16UC1 mm or 32FC1 m)',
        ),
        DeclareLaunchArgument(
            'camera_info',
            default_value='camera/camera_info',
            description="the colour camera's sensor_msgs/CameraInfo (the matcher's camera model)",
        ),
        DeclareLaunchArgument(
            'odom',
            default_value='odom',
            description='nav_msgs/Odometry: keyframe poses, gating, lln/pose in the odometry frame (tf2 is not used)',
        ),
        DeclareLaunchArgument(
            'use_sim_time',
            default_value='false',
            choices=['true', 'false'],
            description='run on /clock (bag replay: lln-bag play --clock, ros2 bag play '
            '--clock), so max_query_age and stamps work on recorded data',
        ),
        DeclareLaunchArgument(
            'namespace', default_value='', description='namespace of the nodes and their relative topics and services'
        ),
        DeclareLaunchArgument(
            'log_level',
            default_value='info',
            choices=['debug', 'info', 'warn', 'error', 'fatal'],
            description='log level of the nodes',
        ),
        DeclareLaunchArgument(
            'visualize',
            default_value='false',
            choices=['true', 'false'],
            description='also start lln_visualizer: `overlay` image (query beside its '
            'best keyframe, matched regions linked) and `markers`',
        ),
        DeclareLaunchArgument(
            'rviz',
            default_value='false',
            choices=['true', 'false'],
            description='also start rviz2 with share/lln_ros/rviz/lln.rviz',
        ),
        DeclareLaunchArgument(
            'dds_profile',
            default_value=EnvironmentVariable(
                'FASTRTPS_DEFAULT_PROFILES_FILE', default_value=PathJoinSubstitution([config, 'fastdds_large_data.xml'])
            ),
            description='Fast DDS XML profile for the started processes (default: '
            '$FASTRTPS_DEFAULT_PROFILES_FILE, else the shipped large-data '
            'profile with a 16 MiB shared-memory segment)',
        ),
        DeclareLaunchArgument(
            'extractor_params',
            default_value=PathJoinSubstitution([config, 'extractor.yaml']),
            description='parameter file of the extractor',
        ),
        DeclareLaunchArgument(
            'matcher_params',
            default_value=PathJoinSubstitution([config, 'matcher.yaml']),
            description='parameter file of the matcher',
        ),
    ]
    # Fast DDS 2.x (Jazzy) reads FASTRTPS_*, 3.x (Kilted and later) FASTDDS_*
    environment = [
        SetEnvironmentVariable(name, LaunchConfiguration('dds_profile'))
        for name in ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')
    ]
    # what every lln_ros node of this launch shares
    ours = dict(package='lln_ros', output='screen', emulate_tty=True, namespace=namespace, ros_arguments=ros_arguments)
    extractor = Node(
        executable='extractor',
        name='lln_extractor',
        **ours,
        parameters=[
            LaunchConfiguration('extractor_params'),
            {
                'image_transport': LaunchConfiguration('image_transport'),
                'reliability': LaunchConfiguration('reliability'),
                'frame_queue': LaunchConfiguration('frame_queue'),
                'publish_keypoints': verify,
                'depth': LaunchConfiguration('depth'),
                'use_sim_time': use_sim_time,
            },
        ],
        remappings=[
            ('image', image),
            ('image/compressed', [image, '/compressed']),
            ('depth/image', LaunchConfiguration('depth_image')),
        ],
    )
    matcher = Node(
        executable='matcher',
        name='lln_matcher',
        **ours,
        parameters=[
            LaunchConfiguration('matcher_params'),
            {
                'mode': LaunchConfiguration('mode'),
                'map_path': LaunchConfiguration('map_path'),
                'verify': verify,
                'use_sim_time': use_sim_time,
            },
        ],
        remappings=[
            (['lln/', LaunchConfiguration('feed')], 'lln/landmarks'),
            ('camera_info', camera_info),
            ('odom', odom),
        ],
    )
    visualizer = Node(
        executable='visualizer',
        name='lln_visualizer',
        **ours,
        condition=IfCondition(LaunchConfiguration('visualize')),
        parameters=[
            {
                'image_transport': LaunchConfiguration('image_transport'),
                'reliability': LaunchConfiguration('reliability'),
                'use_sim_time': use_sim_time,
            }
        ],
        remappings=[('image', image), ('image/compressed', [image, '/compressed'])],
    )
    rviz = Node(
        package='rviz2',
        executable='rviz2',
        name='rviz2',
        output='screen',
        namespace=namespace,
        condition=IfCondition(LaunchConfiguration('rviz')),
        arguments=['-d', PathJoinSubstitution([share, 'rviz', 'lln.rviz'])],
        parameters=[{'use_sim_time': use_sim_time}],
    )
    return LaunchDescription(arguments + environment + [extractor, matcher, visualizer, rviz])
