"""Former name of :mod:`sb3_cql.protocol`, the thesis's evaluation protocol; importing it warns and forwards.

``python -m sb3_cql.benchmark`` still runs ``python -m sb3_cql.protocol`` (with a :class:`DeprecationWarning`), and
``sb3_cql.benchmark.records``, ``.runner``, ``.runs``, ``.report`` and ``.plots`` are the protocol's modules
themselves. Speed scripts are in the repository's ``benchmarks/`` folder.
"""

import warnings

warnings.warn(
    "sb3_cql.benchmark is now sb3_cql.protocol (python -m sb3_cql.protocol); the old name will be removed",
    DeprecationWarning,
    stacklevel=2,
)

from sb3_cql.protocol import *  # noqa: E402, F403  (the old name's public API, unchanged)
from sb3_cql.protocol import __all__  # noqa: E402, F401
from sb3_cql.protocol.runner import ProtocolError as BenchmarkError  # noqa: E402, F401  (the error's former name)
