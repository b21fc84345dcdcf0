"""sb3-cql: Conservative Q-Learning for Stable-Baselines3 and the Panda grasping tasks it learns."""

__version__ = "0.1.0"
