"""The topic names of the lln_ros nodes, in one place (no rclpy).

Every name is relative, so a node's namespace moves them all (`--ros-args -r __ns:=/robot1`, or the
launch file's `namespace:=robot1`: /robot1/lln/candidates), and sits under the `lln/` prefix so it
cannot clash with another package's topics of the same base name (rtabmap publishes its own
`landmarks`). The camera input keeps the image_transport convention (`image`, `image/compressed`),
remapped to the camera's topic; so do the other sensor inputs (`depth/image` registered to the colour
camera, REP 118; `camera_info`, the colour camera's; `odom`, nav_msgs/Odometry).

    extractor  in: image | image/compressed,       out: lln/landmarks, lln/model_info (latched),
                   depth/image (optional)               lln/keypoints (verify), lln/activation
    matcher    in: lln/query, lln/keyframes,        out: lln/candidates, lln/matches,
                   lln/model_info, lln/keypoints,       lln/pose (localization, with odometry poses)
                   camera_info, odom (optional)
    visualizer in: image, lln/candidates,           out: lln/overlay, lln/markers
                   lln/matches
The extractor's lln/landmarks is remapped to the matcher's lln/query (answered) or lln/keyframes
(stored); the launch file does it with `feed:=query|keyframes`.
"""

PREFIX = 'lln/'

IMAGE = 'image'
LANDMARKS = PREFIX + 'landmarks'
MODEL_INFO = PREFIX + 'model_info'
KEYPOINTS = PREFIX + 'keypoints'
ACTIVATION = PREFIX + 'activation'
QUERY = PREFIX + 'query'
KEYFRAMES = PREFIX + 'keyframes'
CANDIDATES = PREFIX + 'candidates'
MATCHES = PREFIX + 'matches'
OVERLAY = PREFIX + 'overlay'
MARKERS = PREFIX + 'markers'
DEPTH = 'depth/image'
CAMERA_INFO = 'camera_info'
ODOM = 'odom'
POSE = PREFIX + 'pose'
