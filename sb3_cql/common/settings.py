"""The settings of the offline algorithms: the errors a setting or a diverged training raises, and the checks that
every algorithm's ``_check_settings`` draws on (each raises one :class:`SettingError` line naming the keyword and its
value)."""

from __future__ import annotations

import numbers
from collections.abc import Iterable
from typing import Any

import numpy as np
import torch as th


class SettingError(ValueError):
    """A keyword argument of an offline algorithm (given to its constructor or to ``load``) that it cannot train with,
    or a replay buffer given as its ``dataset`` that it cannot train on; the message names the keyword and the value."""


class KeywordError(SettingError, TypeError):
    """A keyword argument an offline algorithm does not take: a misspelt one, or SAC's for what it does not train. A
    ``TypeError`` too, as Python's own for an unexpected keyword."""


class ObservationError(SettingError):
    """An observation the policy cannot act on, or the model train on: a NaN or an infinity (from the env, or a wrapper
    of it), named with where it is in the observation."""


def check_finite_observation(observation: Any, what: str = "the observation") -> None:
    """:class:`ObservationError` naming the first NaN or infinity of ``observation`` (one or a batch; an array or a dict
    of them) and its index: torch would fail later on the actor's distribution (``Expected parameter loc ...``)."""
    for key, value in observation.items() if isinstance(observation, dict) else [(None, observation)]:
        array = np.asarray(value)
        if np.issubdtype(array.dtype, np.floating) and not np.isfinite(array).all():
            index = [int(i) for i in np.argwhere(~np.isfinite(array))[0]]
            name = what if key is None else f"{what}[{key!r}]"
            raise ObservationError(f"{name} holds {array[tuple(index)]} at index {index} (shape {list(array.shape)}): every "
                                   "observation must be finite; check the env and its wrappers")  # fmt: skip


def check_keywords(algorithm: str, given: Iterable[str], known: Iterable[str]) -> None:
    """:class:`KeywordError` naming the keywords of ``given`` that are not ``known``, each with the known one it is
    closest to."""
    import difflib

    known = sorted(known)
    unknown = sorted(set(given) - set(known))
    if unknown:
        guesses = [f"{name} (did you mean {close[0]}?)" if (close := difflib.get_close_matches(name, known, 1)) else name
                   for name in unknown]  # fmt: skip
        raise KeywordError(f"{algorithm} got unexpected keyword arguments: {', '.join(guesses)}")


def is_count(value: Any, minimum: int) -> bool:
    """Whether ``value`` is an integer (not a bool) of at least ``minimum``."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool) and value >= minimum


def check_count(name: str, value: Any, minimum: int) -> None:
    """:class:`SettingError` unless the setting ``name`` is an integer of at least ``minimum``."""
    if not is_count(value, minimum):
        raise SettingError(f"{name} must be an integer >= {minimum}, got {value!r}")


#: The most candidates best-of-N draws at each decision, each valued by the critics for every observation of a batch
#: (10**9 of them would ask for tens of GB at the first ``predict``).
MAX_BEST_OF_N = 4096


def check_best_of_n(value: Any) -> None:
    """:class:`SettingError` unless ``best_of_n`` is an integer in [1, :data:`MAX_BEST_OF_N`]."""
    if not is_count(value, 1) or value > MAX_BEST_OF_N:
        raise SettingError(f"best_of_n must be an integer in [1, {MAX_BEST_OF_N}] (the candidate actions drawn and valued "
                           f"at each decision; more would not fit in memory), got {value!r}")  # fmt: skip


def check_fraction(name: str, value: Any, zero: bool = False) -> None:
    """:class:`SettingError` unless the setting ``name`` is a number in (0, 1] (in [0, 1] with ``zero``)."""
    number = isinstance(value, numbers.Real) and not isinstance(value, bool)
    if not (number and (value >= 0 if zero else value > 0) and value <= 1):
        raise SettingError(f"{name} must be in {'[' if zero else '('}0, 1], got {value!r}")


def check_non_negative(names_values: Iterable[tuple[str, Any]], strictly: bool = False) -> None:
    """:class:`SettingError` unless each setting is a number >= 0 (> 0 with ``strictly``)."""
    for name, value in names_values:
        number = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if not number or not (value > 0 if strictly else value >= 0):
            raise SettingError(f"{name} must be a number {'>' if strictly else '>='} 0, got {value!r}")
        if not np.isfinite(value):
            raise SettingError(f"{name} must be a finite number, got {value!r}")


def check_finite(names_values: Iterable[tuple[str, Any]]) -> None:
    """:class:`SettingError` unless each setting is a finite number."""
    for name, value in names_values:
        if not (isinstance(value, numbers.Real) and not isinstance(value, bool) and np.isfinite(value)):
            raise SettingError(f"{name} must be a finite number, got {value!r}")


def check_rate(name: str, value: Any) -> None:
    """:class:`SettingError` unless the learning rate ``name`` is a finite number >= 0, or a schedule (SB3's callable of
    the progress remaining) whose first value is (0: the zoo's ``enjoy`` loads models frozen)."""
    if callable(value) and not isinstance(value, numbers.Real):
        try:
            first = value(1.0)
        except Exception as error:
            raise SettingError(f"{name}: the schedule {value!r} fails at progress 1.0: {error}") from None
        if not (isinstance(first, numbers.Real) and np.isfinite(first) and first >= 0):
            raise SettingError(f"{name} must be a number >= 0, got a schedule starting at {first!r}")
        return
    check_non_negative([(name, value)])


def check_net_arch(net_arch: Any) -> None:
    """:class:`SettingError` unless ``net_arch`` (a policy keyword) is SB3's: ``None``, a list of layer sizes (integers
    >= 1), or a dict of such lists (``pi``, ``qf``)."""
    layers = net_arch.values() if isinstance(net_arch, dict) else [net_arch]
    for sizes in layers:
        if sizes is not None and not (isinstance(sizes, (list, tuple)) and all(is_count(size, 1) for size in sizes)):
            raise SettingError(f"net_arch must be a list of layer sizes (integers >= 1) or a dict of them, got {net_arch!r}")


def check_entropy(ent_coef: Any, target_entropy: Any) -> None:
    """:class:`SettingError` unless SAC's ``ent_coef`` is a finite number >= 0, ``\"auto\"`` or ``\"auto_X\"`` (X > 0, its
    initial value), and ``target_entropy`` is ``\"auto\"`` or a finite number."""
    if isinstance(ent_coef, str):
        initial = ent_coef.partition("_")[2] if ent_coef.startswith("auto_") else "1" if ent_coef == "auto" else ""
        try:
            valid = np.isfinite(float(initial)) and float(initial) > 0
        except ValueError:
            valid = False
        if not valid:
            raise SettingError(f"ent_coef must be a finite number >= 0, 'auto' or 'auto_X' with X > 0, got {ent_coef!r}")
    else:
        check_non_negative([("ent_coef", ent_coef)])
    if not (isinstance(target_entropy, str) and target_entropy == "auto"):
        check_finite([("target_entropy", target_entropy)])


class TrainingDivergedError(FloatingPointError, ValueError):
    """A training loss became NaN or infinite. A ``ValueError`` too, so that RL-Zoo3's tuning prunes the trial
    (it prunes on ``ValueError``) instead of ending the whole study."""


def finite_loss_value(loss: th.Tensor, description: str, step: int, hint: str) -> float:
    """``loss`` as a number; :class:`TrainingDivergedError` naming ``description`` (``"CQL's critic loss"``), the
    gradient ``step`` and a ``hint`` of what to try if it is NaN or infinite."""
    value = loss.item()
    if not np.isfinite(value):
        raise TrainingDivergedError(f"{description} is {value} at gradient step {step}: training diverged ({hint})")
    return value


#: SAC's keywords that an offline algorithm refuses, with why: ``(keyword, the value it accepts, the reason)``.
UNSUPPORTED_SAC_KEYWORDS = (
    ("use_sde", False, "gSDE explores by sampling noise matrices for rollouts; the conservative term and the warm start "
     "draw the policy's actions without it"),
    ("use_sde_at_warmup", False, "gSDE is not supported (use_sde)"),
    ("optimize_memory_usage", False, "the offline data keep each transition's next observation: an episode's last "
     "observation is not the next episode's first"),
)  # fmt: skip


def refuse_unsupported(kwargs: dict[str, Any]) -> None:
    """One line for a SAC keyword set to a value an offline algorithm cannot honour."""
    for keyword, accepted, reason in UNSUPPORTED_SAC_KEYWORDS:
        if kwargs.get(keyword, accepted) != accepted:
            raise SettingError(f"{keyword}={kwargs[keyword]!r} is not supported: {reason}")
