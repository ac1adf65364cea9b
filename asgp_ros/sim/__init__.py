"""ROS-free simulators: the wheelchair and its sensors, an RGB-D room, the Arduino board."""
