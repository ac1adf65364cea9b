"""ROS-free sparse-feature RGB-D visual odometry (Fovis-like) on OpenCV."""
