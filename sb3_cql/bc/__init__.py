from sb3_cql.bc.bc import BC

__all__ = ["BC"]
