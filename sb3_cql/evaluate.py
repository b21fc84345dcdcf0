"""Success rate of a policy on each of the tasks: a model trained on one task, evaluated on all three.

    python -m sb3_cql.evaluate logs/cql/Panda-v0_1/best_model.zip --algo cql -n 100 --seed 0
    python -m sb3_cql.evaluate logs/bc/Panda-v0_1/best_model.zip --algo bc --seeds 50000-50099   # one episode a seed
    python -m sb3_cql.evaluate pid --env Panda-v0 PandaForce-v0 -n 100
    python -m sb3_cql.evaluate pid-regrasp --env PandaForce-v0 -n 100      # the PD controller that regrasps
    python -m sb3_cql.evaluate pid-regrasp-yaw --env PandaForce-v0 -n 100  # ... with a random yaw at each attempt
    python -m sb3_cql.evaluate pid --env Panda-v0 --env-kwargs action_mode:"'delta'"
    python -m sb3_cql.evaluate MODEL.zip --algo cql --env PandaForce-v0 --seeds 50000-50099 --alignment --output out.json

``MODEL`` is a saved SB3 model (``--algo`` is its RL-Zoo3 name: cql, sac, ...) or a PD controller of
``envs.CONTROLLERS``: ``pid``, ``pid-regrasp`` (it reopens and grasps again when it has lost the object),
``pid-regrasp-yaw`` (the same with the hand's yaw drawn at random at each grasp attempt) or ``pid-regrasp-aligned``
(the reference: the fingers close across a fallen cylinder's axis).
A model acts in the action mode it was trained in, the one whose action space is the model's (absolute: the joint
limits, delta: [-1, 1]^9); an ``action_mode`` in ``--env-kwargs`` must be that one. The PD controllers act in the
tasks' default (absolute) mode unless ``--env-kwargs`` gives another.
Episodes are deterministic given ``--seed``: the env is reset with it once, and its own generator seeds the rest
(a PD controller's random yaws are seeded with it too, ``PDController.seed``).
With ``--seeds`` (a range FIRST-LAST or a list), episode i is reset with the i-th seed, and a PD controller seeded
with it: any tool that resets the env with the same seeds replays the same episodes.
With ``--alignment``, each task also gets a histogram of how the fingers closed on a lying cylinder: the angle
between the hand's closing direction and the cylinder's axis (90: across it, the grasp that holds; 0: along it) at
each closing, ``envs.pd_controller.closing_angles``. ``--output`` writes every episode's seed, success and closing
angles to a JSON file, rewritten atomically after each task.
A model that is missing, unreadable or not made for the tasks is reported in one line, with exit status 2.
Ctrl-C (or SIGTERM) ends the evaluation on one line saying what ``--output`` holds (the tasks finished before it),
with status 130 (143), also while the command starts.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import os
import re
import sys
import zipfile
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import gymnasium as gym
import numpy as np
from rl_zoo3.utils import StoreDict
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.monitor import Monitor
from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm
from stable_baselines3.common.vec_env import DummyVecEnv

import envs
from envs.panda_env import check_keywords
from envs.pd_controller import closing_angles
from sb3_cql.data.spaces import check_spaces, default_action_mode, env_kwargs_for, env_name
from sb3_cql.processes import exit_status, run_command

#: The command's name in its messages.
PROG = "python -m sb3_cql.evaluate"
#: The action mode of an env made without ``action_mode``.
DEFAULT_ACTION_MODE = default_action_mode()


@dataclasses.dataclass
class EpisodeOutcome:
    """One evaluation episode: its seed, whether it succeeded, and :func:`envs.pd_controller.closing_angles` of its
    observations (degrees; ``None`` where the cylinder stood)."""

    seed: int
    success: bool
    closing_angles: list[float | None]


def episode_outcomes(
    policy: Any,
    env_id: str,
    seeds: Sequence[int],
    deterministic: bool = True,
    env_kwargs: dict[str, Any] | None = None,
) -> list[EpisodeOutcome]:
    """``policy``'s (an SB3 model or :class:`envs.PDController`) episodes of ``env_id`` made with ``env_kwargs``,
    episode ``i`` reset with ``seeds[i]`` (and a PD controller seeded with it): an episode is replayed by resetting
    the env with its seed, whatever ran before. The policy's state goes from one step to the next, SB3-style.

    :raises ValueError: for a policy whose spaces are not the env's (:func:`~sb3_cql.data.check_spaces`).
    """
    env = gym.make(env_id, **(env_kwargs or {}))
    try:
        check_spaces(policy, env.observation_space, env.action_space, env_name(env, env_id))
        outcomes = []
        for seed in seeds:
            observation, info = env.reset(seed=int(seed))
            if isinstance(policy, envs.PDController):
                policy.seed(int(seed))
            state, episode_start = None, np.ones(1, dtype=bool)
            observations = [observation]
            terminated = truncated = False
            while not (terminated or truncated):
                action, state = policy.predict(observation, state, episode_start, deterministic=deterministic)
                observation, _, terminated, truncated, info = env.step(action)
                observations.append(observation)
                episode_start = np.zeros(1, dtype=bool)
            success = bool(info.get("is_success", False))
            outcomes.append(EpisodeOutcome(int(seed), success, closing_angles(np.stack(observations))))
        return outcomes
    finally:
        env.close()


def episode_successes(
    policy: Any,
    env_id: str,
    seeds: Sequence[int],
    deterministic: bool = True,
    env_kwargs: dict[str, Any] | None = None,
) -> list[bool]:
    """Whether ``policy`` succeeds in each episode of ``env_id``, episode ``i`` reset with ``seeds[i]``
    (:func:`episode_outcomes`, whose parameters these are)."""
    return [outcome.success for outcome in episode_outcomes(policy, env_id, seeds, deterministic, env_kwargs)]


#: Bins (degrees) of the histogram of closing angles that ``--alignment`` prints.
ANGLE_BINS = np.arange(0, 91, 10)


def alignment_summary(outcomes: Sequence[EpisodeOutcome]) -> str:
    """One line on how the fingers closed on lying cylinders in ``outcomes``: a histogram of the closing angles in
    ``ANGLE_BINS``, and how many closings were on an upright cylinder."""
    angles = [angle for outcome in outcomes for angle in outcome.closing_angles if angle is not None]
    upright = sum(angle is None for outcome in outcomes for angle in outcome.closing_angles)
    lying = sum(any(angle is not None for angle in outcome.closing_angles) for outcome in outcomes)
    counts, _ = np.histogram(angles, bins=ANGLE_BINS)
    edges = zip(ANGLE_BINS[:-1], ANGLE_BINS[1:], counts, strict=True)
    bins = ", ".join(f"{low}-{high}: {count}" for low, high, count in edges)
    return (
        f"closings on a lying cylinder by angle between the closing direction and its axis (deg; 90: across it): "
        f"{bins} ({len(angles)} in {lying} episodes; {upright} on an upright cylinder)"
    )


def success_rate(
    policy: Any,
    env_id: str,
    n_episodes: int = 100,
    seed: int = 0,
    deterministic: bool = True,
    env_kwargs: dict[str, Any] | None = None,
    seeds: Sequence[int] | None = None,
) -> float:
    """Fraction of ``n_episodes`` episodes of ``env_id`` (made with ``env_kwargs``) that ``policy`` (an SB3 model or
    :class:`envs.PDController`) succeeds in: SB3's ``evaluate_policy`` on a ``DummyVecEnv`` seeded once with ``seed``,
    whose generator seeds the next episodes (a PD controller is seeded with it too). With ``seeds``, one episode per
    seed, reset with it (:func:`episode_successes`), instead.

    :raises ValueError: for a policy whose ``observation_space`` or ``action_space`` is not the env's.
    """
    if seeds is not None:
        if len(seeds) == 0:
            raise ValueError("seeds is empty: give one seed per episode")
        return float(np.mean(episode_successes(policy, env_id, seeds, deterministic, env_kwargs)))
    env = gym.make(env_id, **(env_kwargs or {}))
    try:
        check_spaces(policy, env.observation_space, env.action_space, env_name(env, env_id))
    except ValueError:
        env.close()
        raise
    vec_env = DummyVecEnv([lambda: Monitor(env)])
    vec_env.seed(seed)
    if isinstance(policy, envs.PDController):
        policy.seed(seed)
    successes: list[bool] = []

    def record_success(local_vars: dict[str, Any], _globals: dict[str, Any]) -> None:
        if local_vars["done"]:
            successes.append(bool(local_vars["info"].get("is_success", False)))

    evaluate_policy(policy, vec_env, n_eval_episodes=n_episodes, deterministic=deterministic, callback=record_success)
    vec_env.close()
    return float(np.mean(successes))


def load_policy(model: str, algo: str | None, env_id: str, env_kwargs: dict[str, Any] | None = None) -> Any:
    """The PD controller named ``model`` in ``envs.CONTROLLERS`` (for ``env_id`` made with ``env_kwargs``), else the SB3
    model saved at ``model`` (``algo``: a key of RL-Zoo3's ALGOS)."""
    if model in envs.CONTROLLERS:
        env = gym.make(env_id, **(env_kwargs or {}))
        controller = envs.PDController.for_env(env, **envs.CONTROLLERS[model])
        env.close()
        return controller
    if algo is None:
        raise ValueError("a saved model needs --algo (cql, sac, ...)")
    from rl_zoo3.utils import ALGOS  # our plugin adds cql

    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}: one of {sorted(ALGOS)}")
    # As the zoo's enjoy does: an off-policy model needs no replay buffer to act.
    kwargs = {"buffer_size": 1} if issubclass(ALGOS[algo], OffPolicyAlgorithm) else {}
    return ALGOS[algo].load(model, device="cpu", **kwargs)


def parse_seeds(item: str) -> range:
    """The seeds of one ``--seeds`` item: a seed ``S`` or the inclusive range ``FIRST-LAST``."""
    match = re.fullmatch(r"(\d+)(?:-(\d+))?", item)
    if match is None:
        raise argparse.ArgumentTypeError(f"{item!r} is neither a seed nor a range FIRST-LAST of seeds (e.g. 50000-50099)")
    first = int(match[1])
    last = first if match[2] is None else int(match[2])
    if last < first:
        raise argparse.ArgumentTypeError(f"{item!r} is an empty range: FIRST-LAST needs FIRST <= LAST")
    return range(first, last + 1)


def format_seeds(seeds: Sequence[int]) -> str:
    """``seeds`` as ``--seeds`` takes them, runs of consecutive seeds as ranges: ``50000-50099``, ``3 17 42``."""
    items = []
    for _, run in itertools.groupby(enumerate(seeds), key=lambda index_seed: index_seed[1] - index_seed[0]):
        run_seeds = [seed for _, seed in run]
        items.append(str(run_seeds[0]) if len(run_seeds) == 1 else f"{run_seeds[0]}-{run_seeds[-1]}")
    return " ".join(items)


class EnvKwargs(StoreDict):
    """RL-Zoo3's ``KEY:VALUE`` dict action, with a usage error for an item that is not one (typically the model's
    path, swallowed when it comes after ``--env-kwargs``)."""

    def __call__(self, parser, namespace, values, option_string=None):
        for item in values:
            key, _, value = item.partition(":")
            try:
                eval(value)  # as StoreDict does next
                valid = bool(key)
            except Exception:  # SyntaxError for the empty value of an item without ":", NameError, ...
                valid = False
            if not valid:
                parser.error(
                    f"{option_string} takes KEY:VALUE items with a Python value (e.g. action_mode:\"'delta'\"), got "
                    f"{item!r} (a string needs quotes; the model goes before {option_string})"
                )
        super().__call__(parser, namespace, values, option_string)


def fail(parser: argparse.ArgumentParser, message: str) -> NoReturn:
    """Exit with status 2, as a usage error does, after one line on stderr (no usage: the arguments parsed)."""
    print(f"{parser.prog}: error: {' '.join(message.split())}", file=sys.stderr)
    raise SystemExit(2)


def model_file(path: str) -> Path | None:
    """The file SB3 reads the model saved at ``path`` from (``path``, or ``path`` + ``.zip``), if there is one."""
    return next((candidate for candidate in (Path(path), Path(f"{path}.zip")) if candidate.is_file()), None)


def check_output(parser: argparse.ArgumentParser, output: Path, model: str) -> None:
    """A one-line error, before any episode, for an ``--output`` that is a folder, the model's own file, or a place
    without write permission."""
    try:
        is_dir, exists = output.is_dir(), output.exists()
    except OSError as error:  # a name too long, ...
        fail(parser, f"--output {output} cannot be written: {error.strerror or error}")
    if is_dir:
        fail(parser, f"--output {output} is a folder: give the path of a JSON file, e.g. {output / 'evaluation.json'}")
    found = model_file(model)
    if found is not None and exists and os.path.samefile(output, found):
        fail(parser, f"--output {output} is the model {model} itself: give another file, e.g. {found.with_suffix('.json')}")
    folder = output.absolute().parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        fail(parser, f"--output {output} cannot be written: {folder} is not a folder this user may write in")


def load_model(parser: argparse.ArgumentParser, path: str, algo: str, env_id: str) -> Any:
    """The SB3 model saved at ``path`` (or ``path`` + ``.zip``, as SB3 reads it), or a one-line error."""
    from rl_zoo3.utils import ALGOS  # our plugin adds cql

    if algo not in ALGOS:
        fail(parser, f"unknown --algo {algo!r}: one of {', '.join(sorted(ALGOS))}")
    found = model_file(path)
    if found is None:
        fail(parser, f"no saved model at {path}" + (" (a folder)" if Path(path).is_dir() else ""))
    from sb3_cql.common.atomic import saved_model_problem

    problem = saved_model_problem(found) if zipfile.is_zipfile(found) else None  # a zip without a model's members
    if problem is not None:
        fail(parser, f"cannot load {found} as a {algo} model: {problem}")
    from sb3_cql.common.offline import OfflineSAC, saved_algorithm

    saved = saved_algorithm(found)  # our algorithms record theirs: another one's model is named as such
    if issubclass(ALGOS[algo], OfflineSAC) and saved is not None and saved not in [c.__name__ for c in ALGOS[algo].__mro__]:
        name = next((key for key, klass in ALGOS.items() if klass.__name__ == saved), saved.lower())
        fail(parser, f"cannot load {found} as a {algo} model: it holds {'an' if saved[0] in 'AEIOU' else 'a'} {saved} model; "
                     f"give --algo {name}")  # fmt: skip
    try:
        return load_policy(str(found), algo, env_id)
    except Exception as error:  # an unreadable file: not a zip, truncated, another algorithm's model, ...
        fail(parser, f"cannot load {found} as a {algo} model ({type(error).__name__}: {error})")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", help=f"path of a saved SB3 model, or a PD controller: {', '.join(envs.CONTROLLERS)}")
    parser.add_argument("--algo", default=None, help="RL-Zoo3 name of the model's algorithm (cql, sac, ...)")
    parser.add_argument("--env", nargs="+", default=list(envs.ENV_IDS), choices=list(envs.ENV_IDS))
    parser.add_argument("-n", "--n-episodes", type=int, default=None,
                        help="episodes per task (default 100; with --seeds, the number of seeds)")  # fmt: skip
    seeding = parser.add_mutually_exclusive_group()
    seeding.add_argument("--seed", type=int, default=0,
                         help="seed of the env's first reset; its generator seeds the next episodes (default 0)")  # fmt: skip
    seeding.add_argument("--seeds", type=parse_seeds, nargs="+", metavar="SEEDS",
                         help="one episode per seed, reset with it: a range FIRST-LAST (inclusive) and/or seeds, "
                              "e.g. 50000-50099 or 3 17 42")  # fmt: skip
    parser.add_argument("--stochastic", action="store_true", help="sample actions instead of the deterministic ones")
    parser.add_argument("--env-kwargs", type=str, nargs="+", action=EnvKwargs, default={},
                        help="env keywords as the zoo's, e.g. action_mode:\"'delta'\" (a model's action mode is read "
                             "from its action space: an action_mode given must be that one)")  # fmt: skip
    parser.add_argument("--alignment", action="store_true",
                        help="also print how the fingers closed on lying cylinders: a histogram of the angle between "
                             "the closing direction and the cylinder's axis (needs --seeds)")  # fmt: skip
    parser.add_argument("--output", type=Path, default=None,
                        help="write each episode's seed, success and closing angles to this JSON file "
                             "(needs --seeds)")  # fmt: skip
    args = parser.parse_args(argv)
    seeds = None if args.seeds is None else list(itertools.chain.from_iterable(args.seeds))
    if seeds is None and (args.alignment or args.output is not None):
        parser.error("--alignment and --output need --seeds (one episode per seed)")
    if seeds is not None and args.n_episodes not in (None, len(seeds)):
        parser.error(f"-n {args.n_episodes} conflicts with --seeds, which gives {len(seeds)} episodes (one per seed)")
    n_episodes = len(seeds) if seeds is not None else 100 if args.n_episodes is None else args.n_episodes
    if n_episodes < 1:
        parser.error(f"-n needs at least 1 episode, got {n_episodes}")
    if args.seed < 0:
        fail(parser, f"--seed must be >= 0 (numpy seeds), got {args.seed}")
    for option, values in (("--env", args.env), ("--seeds", seeds or [])):  # a repeat would count an episode twice
        repeated = next((value for value, count in Counter(values).items() if count > 1), None)
        if repeated is not None:
            fail(parser, f"{option}: {repeated} is given more than once (ranges included): give each once")
    try:
        check_keywords(args.env_kwargs)
    except TypeError as error:
        fail(parser, f"--env-kwargs: {error}")
    if args.output is not None:
        check_output(parser, args.output, args.model)
    written: list[str] = []  # the tasks --output holds
    try:
        _evaluate(parser, args, seeds, n_episodes, written)
    except KeyboardInterrupt as interrupt:
        kept = f"{args.output} holds the tasks finished before ({', '.join(written)})" if written else "nothing written"
        print(f"interrupted: {kept}", file=sys.stderr)
        raise SystemExit(exit_status(interrupt)) from None


def _evaluate(
    parser: argparse.ArgumentParser, args: argparse.Namespace, seeds: list[int] | None, n_episodes: int, written: list[str]
) -> None:
    """The evaluation :func:`main` asks for, task by task, each task appended to ``written`` once ``--output`` holds it."""
    episodes = f"seed {args.seed}" if seeds is None else f"seeds {format_seeds(seeds)}"
    if args.model in envs.CONTROLLERS:
        model, env_kwargs = None, {env_id: args.env_kwargs for env_id in args.env}
    else:
        if args.algo is None:
            parser.error("a saved model needs --algo (cql, sac, ...)")
        model = load_model(parser, args.model, args.algo, args.env[0])  # loaded once
        env_kwargs = {}
        for env_id in args.env:  # every task checked before the first episode
            try:
                env_kwargs[env_id] = env_kwargs_for(model, env_id, args.env_kwargs)
            except (ValueError, TypeError) as error:  # TypeError: a keyword the env does not take
                fail(parser, f"{args.model}: {error}")
    tasks: dict[str, Any] = {}
    unwritable: list[str] = []
    for env_id in args.env:
        # PD: one per task, for its action mode and physics
        try:
            policy = model if model is not None else load_policy(args.model, args.algo, env_id, env_kwargs[env_id])
        except (ValueError, TypeError) as error:  # an action mode or a keyword the env does not take
            fail(parser, f"{args.model} on {env_id}: {error}")
        action_mode = env_kwargs[env_id].get("action_mode", DEFAULT_ACTION_MODE)
        if seeds is None:
            rate = success_rate(policy, env_id, n_episodes, args.seed, not args.stochastic, env_kwargs[env_id])
        else:
            outcomes = episode_outcomes(policy, env_id, seeds, not args.stochastic, env_kwargs[env_id])
            rate = float(np.mean([outcome.success for outcome in outcomes]))
            tasks[env_id] = {
                "success_rate": rate,
                "action_mode": action_mode,
                "episodes": [dataclasses.asdict(outcome) for outcome in outcomes],
            }
        if args.output is not None and not unwritable:
            from sb3_cql.files import write_json

            record = {"model": args.model, "algo": args.algo, "deterministic": not args.stochastic, "tasks": tasks}
            try:
                write_json(args.output, record)  # after each task: a killed evaluation keeps the tasks it finished
                written.append(env_id)
            except OSError as error:  # the results are still printed, and the command ends on one line at the end
                unwritable.append(f"cannot write --output {args.output} ({error.strerror or error}): the results are "
                                  "the lines printed")  # fmt: skip
        # Printed once recorded: a task whose line is out is in --output.
        print(f"{env_id}: success rate {rate:.3f} over {n_episodes} episodes ({episodes}, {action_mode} actions)", flush=True)
        if args.alignment:
            print(f"{env_id}: {alignment_summary(outcomes)}", flush=True)
    if unwritable:
        fail(parser, unwritable[0])


if __name__ == "__main__":
    run_command(main)
