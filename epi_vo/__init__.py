"""epi_vo: monocular visual odometry that says when a pose cannot be trusted.

Layers: ``core`` (numpy and cv2 only) <- ``io`` (bags, messages; no rclpy) <- ``ros`` (rclpy front doors)
and ``tools`` (replay, benchmark, report); ``cli`` is the ``epi-vo`` front end. See docs/design.md.
"""

__version__ = "0.1.0"
