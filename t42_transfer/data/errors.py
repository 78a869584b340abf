"""Errors for data files that cannot be used, each naming the file and what is wrong.

They are ``ValueError``s: the file's content is the bad value.  The file comes
first in the message so a user with many bags knows at once which one to look at.
"""

from __future__ import annotations

import os


class DataFileError(ValueError):
    """A data file that cannot be turned into trajectories."""

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        # Both parts go to ``args`` so the exception pickles and unpickles intact.
        super().__init__(os.fspath(path), problem)
        self.path = os.fspath(path)
        self.problem = problem

    def __str__(self) -> str:
        return f"{self.path}: {self.problem}"


class BagError(DataFileError):
    """A rosbag2 bag that is missing, damaged beyond recovery, or breaks the hand wire format."""


class PickleFileError(DataFileError):
    """A pickle file that refers to a forbidden global or lacks the expected layout."""
