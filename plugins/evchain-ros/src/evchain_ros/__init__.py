"""evchain-ros: DVS events (dvs_msgs/EventArray) in ROS 1 and ROS 2 bags, via rosbags."""

__version__ = "0.1.0"
