"""File formats read and written by lidarcal (kept light: importing this package imports
nothing heavy; import the submodule you need).

- :mod:`lidarcal.io.dataset`: the dataset contract (docs/dataset-format.md): read, validate,
  write.
- :mod:`lidarcal.io.images`: image files (every way one can fail named); re-exported by
  :mod:`lidarcal.io.dataset`, as is :class:`DatasetError` (kept in :mod:`lidarcal.io.errors`).
- :mod:`lidarcal.io.bag`: ROS 1 / ROS 2 bags (through rosbags) into a dataset folder, built on
  :mod:`lidarcal.io.bag_read` (opening, topics, clocks, LaserScan),
  :mod:`lidarcal.io.bag_angles` (the turntable angle stream), :mod:`lidarcal.io.bag_frames`
  (images), :mod:`lidarcal.io.bag_combine` (still scans and frames combined) and
  :mod:`lidarcal.io.bag_write` (CSV/PNG out, the output folder written atomically).
- :mod:`lidarcal.io.bag_views`: a one-board bag into photo + scan pairs (``import --views``).
- :mod:`lidarcal.io.rig`: RIG.json, what a bag cannot hold.
- :mod:`lidarcal.io.clouds`: point clouds out (PLY, PCD, VTP, CSV) and back in.
- :mod:`lidarcal.io.pairs`: photo + scan pairs of the one-board calibration (``lidarcal planes``).
"""
