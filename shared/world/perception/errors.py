"""Exceptions of the perception module (each message says what is wrong and, where it can, what to do)."""
from __future__ import annotations


class PerceptionError(ValueError):
    """Input that cannot be turned into an object: a bad cloud, no object in it, an ambiguous scene."""


class CloudFileError(PerceptionError):
    """A file that cannot be read as a point cloud (missing, empty, malformed, a mesh, wrong type)."""
