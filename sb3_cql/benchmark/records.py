"""Former name of :mod:`sb3_cql.protocol.records`: this name is that module itself."""

import sys

from sb3_cql.protocol import records

sys.modules[__name__] = records
