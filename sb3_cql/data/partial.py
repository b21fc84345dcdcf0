"""The files of a dataset being written: the names of :mod:`sb3_cql.data.store`, their home, under this module's
older path."""

from sb3_cql.data.store import (
    CRASH_AT_ENV,
    CRASH_POINTS,
    NO_SPACE,
    WRITE_BLOCK,
    DatasetError,
    DatasetFiles,
    crash_point,
    partial_summary,
)
from sb3_cql.files import write_atomically

__all__ = [
    "CRASH_AT_ENV",
    "CRASH_POINTS",
    "NO_SPACE",
    "WRITE_BLOCK",
    "DatasetError",
    "DatasetFiles",
    "crash_point",
    "partial_summary",
    "write_atomically",
]
