"""Zoo commands that end on one line, ``python -m rl_zoo3.<command>: error: ...`` with status 2, where the input is
at fault: our errors that say what to fix, a ``KEY:VALUE`` the zoo cannot evaluate, a schedule it cannot read."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any, NoReturn

from envs.config import ConfigError
from sb3_cql.common import SettingError, TrainingDivergedError
from sb3_cql.data.errors import DatasetError

#: Our errors that say what to fix in the settings, the data or the task.
INPUT_ERRORS = (SettingError, TrainingDivergedError, DatasetError, ConfigError)
#: The hyperparameters read as linear schedules when a string, ``lin_<initial value>``: the zoo reads the first itself.
SCHEDULE_KEYS = ("learning_rate", "actor_learning_rate")


def fail(message: str, item: str = "") -> NoReturn:
    """End the command on one line, ``python -m rl_zoo3.<command>: error: [ITEM: ]MESSAGE``, with status 2."""
    print(f"python -m rl_zoo3.{Path(sys.argv[0]).stem}: error: {item + ': ' if item else ''}{' '.join(message.split())}",
          file=sys.stderr)  # fmt: skip
    raise SystemExit(2) from None


def store_dict_call(call: Any) -> Any:
    """The zoo's ``StoreDict.__call__`` (``KEY:VALUE`` items): a VALUE that Python cannot evaluate is one line."""

    @functools.wraps(call)
    def __call__(self: Any, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        for item in values:
            key, _, value = item.partition(":")
            try:
                eval(value)  # as the zoo does next
            except Exception as error:
                fail(f"{type(error).__name__}: {error}; write KEY:VALUE with a Python value: a number as it is "
                     f"(batch_size:64), a string in quotes inside the shell's ({key or 'KEY'}:\"'{value}'\")",
                     f"{option_string} {item}")  # fmt: skip
        call(self, parser, namespace, values, option_string)

    return __call__


def read_schedules(hyperparams: dict[str, Any]) -> None:
    """One line for a :data:`SCHEDULE_KEYS` string that is not ``lin_<initial value>``; the zoo's linear schedule for
    each of the others (those it does not read itself)."""
    from rl_zoo3.utils import SimpleLinearSchedule  # (not on import: the zoo's import runs the plugin, which needs us)

    for key in SCHEDULE_KEYS:
        if isinstance(value := hyperparams.get(key), str):
            schedule, _, initial = value.partition("_")
            try:
                rate = float(initial) if schedule == "lin" else 0.0
            except ValueError:
                rate = 0.0
            if not rate > 0:
                fail(f"{key} must be a number >= 0 or a linear schedule 'lin_<initial value>'; e.g. {key}:0.0003 or "
                     f"{key}:\"'lin_0.0003'\"", f"--hyperparams {key}:{value!r}")  # fmt: skip
            if key != SCHEDULE_KEYS[0]:
                hyperparams[key] = SimpleLinearSchedule(rate)
