"""Exceptions of the object library (each names the object or file and the problem)."""
from __future__ import annotations


class ObjectLoadError(ValueError):
    """An object id or mesh file that cannot be turned into an ObjectModel.

    The message always names the id or the file, and says what is wrong with it
    (unsupported type, unparsable, empty, not in metres, encloses no volume, ...).
    """


class UnknownObjectError(ObjectLoadError):
    """An id that is not in the library (and not a path to an existing mesh file)."""


class SplitError(ValueError):
    """An object used in a split it does not belong to (e.g. a test object in training)."""
