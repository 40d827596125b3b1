"""File formats beyond the dataset contract (imports nothing heavy).

``lidarcal.io.pairs``: a folder of camera photo + LiDAR scan pairs (``lidarcal planes``).
"""
