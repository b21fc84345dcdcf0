"""``python -m sb3_cql.benchmark``: the protocol's former command, now ``python -m sb3_cql.protocol``."""

import sys
import warnings

if __name__ == "__main__":
    warnings.warn("python -m sb3_cql.benchmark is now python -m sb3_cql.protocol", DeprecationWarning, stacklevel=1)
    print("python -m sb3_cql.benchmark is now python -m sb3_cql.protocol; running it", file=sys.stderr)
    from sb3_cql.processes import run_command
    from sb3_cql.protocol.__main__ import main

    run_command(main)
