"""ROS 2 interchange (docs/ros.md): results as ROS 2 messages in an MCAP bag, without ROS.

``messages`` builds the messages (rosbags' typestore of ROS 2 Jazzy, with ``octomap_msgs``
registered from its ``.msg`` text), ``bag`` writes them to an MCAP file under coopmap's output
rules, and ``export`` turns a result folder into the bag's topics; ``live_view`` serves the same
topics to Foxglove over a WebSocket while the work runs.
"""
