"""epi_vo: monocular visual odometry that says when a pose cannot be trusted.

The core (camera, frontend, geometry, pipeline) imports numpy and cv2 only; ``epi_vo.ros.node`` is the only
module importing rclpy.
"""

__version__ = "0.1.0"
