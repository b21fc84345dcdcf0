"""Zoo commands that end on one line, ``python -m rl_zoo3.<command>: error: ...`` with status 2, where the input is
at fault: our errors that say what to fix, a ``KEY:VALUE`` the zoo cannot evaluate, a hyperparameter nobody takes, a
schedule the zoo cannot read. Any other error is a bug, shown with its traceback."""

from __future__ import annotations

import functools
import sys
from pathlib import Path
from typing import Any, NoReturn

#: ``rl_zoo3.train``'s name in its error lines.
PROG = "python -m rl_zoo3.train"
#: Our errors that say what to fix in the command line, the config or the data, as ``(module, class)``.
INPUT_ERRORS = (
    ("sb3_cql.data.replay", "DatasetError"),
    ("sb3_cql.common.offline", "SettingError"),
    ("sb3_cql.cql.cql", "TrainingDivergedError"),
    ("envs.config", "ConfigError"),
)
#: The keys of a config (and of ``--hyperparams``) that the zoo takes out before it makes the model: with the
#: keywords of the algorithm's class, the keys it takes.
ZOO_KEYS = ("n_timesteps", "n_envs", "normalize", "env_wrapper", "vec_env_wrapper", "frame_stack", "callback",
            "monitor_kwargs", "env_kwargs", "noise_type", "noise_std")  # fmt: skip
#: The hyperparameters whose string values are read as schedules, ``lin_<initial value>``: the zoo's
#: ``learning_rate``, and our algorithms' ``actor_learning_rate`` (read by :func:`read_schedules`).
SCHEDULE_KEYS = ("learning_rate", "actor_learning_rate")
#: Those of :data:`SCHEDULE_KEYS` that the zoo reads itself (``ExperimentManager._preprocess_schedules``).
ZOO_SCHEDULE_KEYS = ("learning_rate",)


def input_error(error: BaseException) -> bool:
    """Whether ``error`` is one of :data:`INPUT_ERRORS`, looked up in the modules loaded: a run that never loaded a
    dataset cannot have a ``DatasetError``, and imports no Minari to check it."""
    return any(isinstance(error, getattr(sys.modules[module], name)) for module, name in INPUT_ERRORS if module in sys.modules)


def fail(message: str, prog: str = PROG) -> NoReturn:
    """End the command on one line, ``PROG: error: MESSAGE``, with status 2 (a usage error's)."""
    print(f"{prog}: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2) from None


def zoo_parse_error(
    option: str, item: str, problem: BaseException | str, hint: str | None = None, prog: str = PROG
) -> NoReturn:
    """End a zoo command on one line for a ``KEY:VALUE`` item of ``option`` (``--hyperparams``, ``--env-kwargs``) that
    the zoo cannot read (it evaluates VALUE as Python): what is wrong, and ``hint`` or what to type instead."""
    key, _, value = item.partition(":")
    why = f"{type(problem).__name__}: {problem}" if isinstance(problem, BaseException) else problem
    if hint is None:
        hint = (f"write KEY:VALUE with a Python value: a number as it is (batch_size:64), a string in quotes "
                f"inside the shell's ({key or 'KEY'}:\"'{value}'\")")  # fmt: skip
    print(f"{prog}: error: {option} {item}: {' '.join(why.split())}; {hint}", file=sys.stderr)
    raise SystemExit(2)


def store_dict_call(store_dict: type) -> Any:
    """The zoo's ``StoreDict.__call__`` (``KEY:VALUE`` items, VALUE evaluated as Python), a value that does not
    evaluate, or an item without a key, ending the command on :func:`zoo_parse_error`'s line."""
    call = store_dict.__call__

    @functools.wraps(call)
    def __call__(self: Any, parser: Any, namespace: Any, values: Any, option_string: Any = None) -> None:
        prog = f"python -m rl_zoo3.{Path(parser.prog).stem}"
        for item in values:
            key, separator, value = item.partition(":")
            if not key or not separator:
                zoo_parse_error(option_string, item, "not KEY:VALUE", prog=prog)
            try:
                eval(value)  # as the zoo does next
            except Exception as error:
                zoo_parse_error(option_string, item, error, prog=prog)
        call(self, parser, namespace, values, option_string)

    __call__._sb3_cql_wrapped = True  # type: ignore[attr-defined]
    return __call__


def check_hyperparameters(algo: type, hyperparams: dict[str, Any]) -> None:
    """Before the zoo reads them: a key that neither the zoo nor ``algo`` takes is a
    :class:`~sb3_cql.common.offline.KeywordError` naming the closest one; a schedule that is neither a number nor
    ``lin_<initial value>`` is :func:`zoo_parse_error`'s line."""
    refuse = getattr(algo, "refuse_unknown_keywords", None)
    if refuse is not None:
        refuse([key for key in hyperparams if key not in ZOO_KEYS])
    for key in SCHEDULE_KEYS:
        value = hyperparams.get(key)
        if isinstance(value, str):
            schedule, _, initial = value.partition("_")
            try:
                valid = schedule == "lin" and float(initial) > 0
            except ValueError:
                valid = False
            if not valid:
                zoo_parse_error("--hyperparams", f"{key}:{value!r}", f"{key} must be a number >= 0 or a linear schedule "
                                f"'lin_<initial value>'", f"e.g. {key}:0.0003 or {key}:\"'lin_0.0003'\"")  # fmt: skip


def read_schedules(hyperparams: dict[str, Any]) -> None:
    """The ``lin_<initial value>`` strings of :data:`SCHEDULE_KEYS` that the zoo does not read itself
    (:data:`ZOO_SCHEDULE_KEYS`), as the zoo's linear schedules, after :func:`check_hyperparameters`."""
    from rl_zoo3.utils import SimpleLinearSchedule  # (with the zoo, not with this module)

    for key in SCHEDULE_KEYS:
        if key not in ZOO_SCHEDULE_KEYS and isinstance(hyperparams.get(key), str):
            hyperparams[key] = SimpleLinearSchedule(float(hyperparams[key].partition("_")[2]))
