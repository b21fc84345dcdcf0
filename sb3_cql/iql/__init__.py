from sb3_cql.iql.iql import IQL, expectile_loss
from sb3_cql.iql.policies import CnnPolicy, IQLPolicy, MlpPolicy, MultiInputPolicy

__all__ = ["IQL", "CnnPolicy", "IQLPolicy", "MlpPolicy", "MultiInputPolicy", "expectile_loss"]
