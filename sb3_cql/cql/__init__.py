from sb3_cql.common.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, NormalizedFlatten
from sb3_cql.cql.cal_ql import CalQL
from sb3_cql.cql.cql import CQL

__all__ = ["CQL", "CalQL", "CnnPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten"]
