"""Former name of :mod:`sb3_cql.protocol.report`: this name is that module itself."""

import sys

from sb3_cql.protocol import report

sys.modules[__name__] = report
