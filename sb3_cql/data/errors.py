"""The data package's error: every module of it raises one, so it sits below them all."""


class DatasetError(ValueError):
    """A dataset that is missing, unreadable, or does not fit the environment."""
