"""Pure processing: stitching, 3D mapping, defect detection and their metrics.

Functions here take arrays and return arrays and dataclasses; they never touch the
database or the network.
"""
