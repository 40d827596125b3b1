"""The bad-input error of every reader: :class:`DatasetError` (documented, and imported, as
``lidarcal.io.dataset.DatasetError``; kept in this small module so that the format readers
beside :mod:`lidarcal.io.dataset` can raise it without importing it)."""

from __future__ import annotations

import os


class DatasetError(Exception):
    """Bad input: ``str(err)`` is ``"FILE: what is wrong; what to do"``."""

    __module__ = "lidarcal.io.dataset"  # where it is documented and imported from

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # picklable (worker processes return it), with both fields
        return (type(self), (self.path, self.problem))
