"""Recordings and the black box, in the front process (docs/recording.md): recorder.py (the drain of
the control loop's sample ring, writer threads, requests), bag.py (one rosbag2 MCAP bag with the ROS
graph's topics and types)."""
