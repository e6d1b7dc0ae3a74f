"""Rig calibration from a ChArUco cuboid: target, detection, intrinsics, bundle adjustment, calibration file."""
