"""sb3-cql: Conservative Q-Learning for Stable-Baselines3 and the Panda grasping tasks it learns."""

import sys

__version__ = "0.1.0"

if getattr(sys, "argv", [""])[:1] == ["-m"]:  # `python -m sb3_cql....` importing its packages: Ctrl-C is one line
    from sb3_cql.processes import quiet_command_startup

    quiet_command_startup()


def __getattr__(name: str):
    # CQL, CalQL, IQL and BC load torch and SB3: import it on first use, so that `python -m sb3_cql.data` and the dataset
    # collection workers start without them.
    if name == "CQL":
        from sb3_cql.cql import CQL

        return CQL
    if name == "CalQL":
        from sb3_cql.cql import CalQL

        return CalQL
    if name == "BC":
        from sb3_cql.bc import BC

        return BC
    if name == "IQL":
        from sb3_cql.iql import IQL

        return IQL
    raise AttributeError(f"module 'sb3_cql' has no attribute {name!r}")


__all__ = ["BC", "CQL", "CalQL", "IQL", "__version__"]
