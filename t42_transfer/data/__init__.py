"""Data layer: trajectories in memory, rosbag2 bags on disk, the public T42 files."""

from t42_transfer.data.trajectory import Trajectory, TrajectorySet, split_by_fraction

__all__ = ["Trajectory", "TrajectorySet", "split_by_fraction"]
