"""``eval_freq``, ``n_eval_episodes`` and ``save_freq`` in a config: the zoo has command-line options for them only. A
config's value replaces the option's default; the option given on the command line wins, even at the default's value
(``--eval-episodes 5``)."""

from __future__ import annotations

import argparse
import sys
from typing import Any

#: ``train.py``'s defaults of ``--eval-freq``, ``--eval-episodes`` and ``--save-freq`` (no checkpoints).
ZOO_DEFAULT_EVAL_FREQ, ZOO_DEFAULT_EVAL_EPISODES, ZOO_DEFAULT_SAVE_FREQ = 25_000, 5, -1
#: The ``rl_zoo3.train`` options a config key replaces while the option is at its default, each with that default and
#: the ``ExperimentManager`` attribute it sets, which is also the config key.
CONFIG_OPTIONS = {
    "--eval-freq": (ZOO_DEFAULT_EVAL_FREQ, "eval_freq"),
    "--eval-episodes": (ZOO_DEFAULT_EVAL_EPISODES, "n_eval_episodes"),
    "--save-freq": (ZOO_DEFAULT_SAVE_FREQ, "save_freq"),
}


def given_on_command_line(option: str, argv: list[str] | None = None) -> bool:
    """Whether ``option`` is in ``argv`` (default ``sys.argv[1:]``, what train.py parses), spelt any way argparse
    takes it: ``--eval-freq 5``, ``--eval-freq=5`` or an abbreviation (``--eval-fr 5``).

    The command line is the only record: the zoo's Namespace holds values and its parser is local to ``train()``. A
    parser of this one option reads it by argparse's rules, as the zoo's did.
    """
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    parser.add_argument(option, dest="given", nargs="?", default=argparse.SUPPRESS)
    try:
        known, _ = parser.parse_known_args(sys.argv[1:] if argv is None else argv)
    except argparse.ArgumentError:  # the option is there, in a form a parser of it alone rejects
        return True
    return hasattr(known, "given")


def apply_config_options(manager: Any, hyperparams: dict[str, Any]) -> None:
    """Take the :data:`CONFIG_OPTIONS` keys out of ``hyperparams`` (the saved config keeps them), setting each on
    ``manager`` where its option was left at the default."""
    for option, (default, attribute) in CONFIG_OPTIONS.items():
        value = hyperparams.pop(attribute, None)
        if value is not None and getattr(manager, attribute) == default and not given_on_command_line(option):
            setattr(manager, attribute, int(value))
