"""Every ROS message encode/decode of lln_ros, in one place: this package (the brief: one module owns
the codecs). Algorithm code stays ROS-free. `from lln_ros.ros import msgs` and `msgs.X` for any codec.

    headers   make_header / stamp_to_ns, and the stamp checks every table and answer goes through
    clouds    typed tables as sensor_msgs/PointCloud2: landmarks, candidates, matches
    keypoints the keypoints table (verify mode), with an optional depth field
    images    sensor_msgs/Image and CompressedImage <-> uint8 arrays
    geometry  sensor_msgs/CameraInfo, REP 118 depth images, nav_msgs/Odometry, PoseWithCovarianceStamped

Typed tables travel as `sensor_msgs/PointCloud2`: height 1, one row (point) per record,
little-endian, is_dense true. A table is a numpy structured array on the Python side:

    cloud = array_to_cloud(records, header)              # any structured array
    records = cloud_to_array(cloud, required=[('score', PointField.FLOAT32, 1)])

The specific tables:

    landmarks   landmarks_to_cloud(lset, header) / cloud_to_landmarks(msg, expected_dim=None)
                row 0 = the whole image, rows 1..n = the landmarks by descending score
                fields u v w h score (FLOAT32), descriptor (FLOAT32, count D)
    candidates  candidates_to_cloud(rows, header) / cloud_to_candidates(msg)
                keyframe_id (UINT32), score holistic_score (FLOAT32), stamp_sec (INT32),
                stamp_nanosec (UINT32), plus any extra FLOAT32 fields (inliers, sequence_score, ...)
    keypoints   keypoints_to_cloud(kps, header) / cloud_to_keypoints(msg, image_size, scale)
                one row per ORB keypoint (zero rows: a textureless image), u v size angle response
                (FLOAT32, original image pixels), octave (INT32), descriptor (UINT8, count 32)
    matches     matches_to_cloud(rows, header) / cloud_to_matches(msg)
                keyframe_id (UINT32), query_u query_v map_u map_v cell_w cell_h similarity weight
                (FLOAT32)

Images: image_to_array / compressed_to_array (message -> uint8 array + channel order) and
array_to_image / array_to_compressed (array -> message).

Every malformed message ends in lln_ros.errors.MessageError with a message naming the problem.
Decoders that take limits (max_rows, limits, max_pixels; see lln_ros.core.limits) check the sizes a
message declares before allocating anything from them, and raise LimitError (a MessageError).
"""

from .clouds import *  # noqa: F401,F403
from .clouds import __all__ as _clouds
from .geometry import *  # noqa: F401,F403
from .geometry import __all__ as _geometry
from .headers import *  # noqa: F401,F403
from .headers import __all__ as _headers
from .images import *  # noqa: F401,F403
from .images import __all__ as _images
from .keypoints import *  # noqa: F401,F403
from .keypoints import __all__ as _keypoints

__all__ = [*_headers, *_clouds, *_keypoints, *_images, *_geometry]
