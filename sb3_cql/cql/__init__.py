from sb3_cql.cql.cql import CQL, TrainingDivergedError
from sb3_cql.cql.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, NormalizedFlatten

__all__ = ["CQL", "CnnPolicy", "MlpPolicy", "MultiInputPolicy", "NormalizedFlatten", "TrainingDivergedError"]
