"""File formats read and written by lidarcal (``bag``: ROS 1 / ROS 2 bags through rosbags).

Nothing heavy is imported here: import the submodule you need.
"""
