"""ROS 2 for sumoco: ``sumoco ros2`` (a run on ROS 2 topics, egos driven from ROS 2) and
``sumoco export rosbag2`` (a recording as a rosbag2). The frame conventions live in
``frames`` (no ROS import); ``messages`` builds the ROS messages, ``node`` is the live
bridge, ``bag`` the exporter. Needs the ``ros2`` extra (ROS 2 Kilted wheels)."""
