"""File formats (kept light: importing this package imports nothing heavy).

- :mod:`lidarcal.io.clouds`: point clouds out (PLY, PCD, VTP, CSV) and back in.
"""
