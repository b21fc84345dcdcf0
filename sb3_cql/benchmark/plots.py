"""Former name of :mod:`sb3_cql.protocol.plots`: this name is that module itself."""

import sys

from sb3_cql.protocol import plots

sys.modules[__name__] = plots
