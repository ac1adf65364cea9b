"""Recordings in and out: bag files, and their replay into a running ROS 2 system.

* :mod:`asgp_ros.recording.bags` -- reading, writing and repairing bags with the
  pure-Python ``rosbags`` (ROS 1 ``.bag``, ROS 2 sqlite3 and mcap; no ROS install needed);
* :mod:`asgp_ros.recording.replay` -- publishing a bag with ``/clock`` (``asgp replay``;
  rclpy is imported only when a replay starts).

Bag I/O does not know where the data come from: it imports neither the simulator nor the
learning side (the simulator writes its recordings through it). Nothing is imported here.
"""
