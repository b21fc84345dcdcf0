"""Former name of :mod:`sb3_cql.protocol.runs`: this name is that module itself."""

import sys

from sb3_cql.protocol import runs

sys.modules[__name__] = runs
