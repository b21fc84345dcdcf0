"""Former name of :mod:`sb3_cql.protocol.runner`: this name is that module itself."""

import sys

from sb3_cql.protocol import runner

sys.modules[__name__] = runner
