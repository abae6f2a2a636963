"""ROS: bags in (``rosbag``: ROS 1, ROS 2 sqlite3 or MCAP, through rosbags; ``cut_mcap`` for an
MCAP cut short) and out (``bag_writer``). Needs the ``ros`` extra."""
