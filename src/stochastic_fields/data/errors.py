"""The one exception every dataset loader raises for bad input."""

from __future__ import annotations

from pathlib import Path


class DatasetError(ValueError):
    """A dataset on disk cannot be loaded as asked.

    The message always names the file (or folder) and the problem, e.g. a missing image, a pose
    count that does not match the image count, wrong array shapes, NaN poses, near >= far, a
    split that leaves no training or no test view, or an unknown format.

    Attributes:
        path: the offending file or folder.
        problem: what is wrong with it.
    """

    def __init__(self, path: str | Path, problem: str):
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")
