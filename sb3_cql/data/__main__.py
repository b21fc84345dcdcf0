"""Command line of the datasets: ``python -m sb3_cql.data collect ...`` and ``python -m sb3_cql.data info ID``.

python -m sb3_cql.data collect --env Panda-v0 --policy pid --episodes 10000 --seed 0 --workers 2
python -m sb3_cql.data collect --env Panda-v0 --policy noisy --noise 0.03 --episodes 1000
python -m sb3_cql.data collect --env Panda-v0 --policy noisy-regrasp --episodes 10000 --ray auto
python -m sb3_cql.data collect --env PandaForce-v0 --policy noisy-regrasp-yaw --action-mode delta --episodes 1000
python -m sb3_cql.data collect --env Panda-v0 --policy logs/sac/Panda-v0_1/best_model.zip --algo sac
python -m sb3_cql.data mix --dataset-id sb3cql/Panda-v0/mixed-v0 sb3cql/Panda-v0/pid-v0 sb3cql/Panda-v0/noisy-v0
python -m sb3_cql.data info sb3cql/Panda-v0/pid-v0

Ctrl-C (or SIGTERM) stops a collection with one line saying how many episodes are kept (exit status 130, 143 for
SIGTERM); the same command resumes it. A model policy acts in the action mode it was trained in (``--action-mode``
may only repeat it). Any error (a missing, partial or damaged dataset, one being written, a full disk, ...) is one
line on stderr (exit status 2).
"""

from __future__ import annotations

import argparse
import json
import sys

import gymnasium

import envs
from sb3_cql.cluster import ClusterError
from sb3_cql.data.collection import WRITE_EVERY, collect_dataset, mix_datasets
from sb3_cql.data.errors import DatasetError
from sb3_cql.data.ids import POLICIES, dataset_path
from sb3_cql.data.rollouts import CollectionSpec, model_action_mode
from sb3_cql.data.store import load_dataset
from sb3_cql.processes import exit_status, run_command

PROG = "python -m sb3_cql.data"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog=PROG, description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)

    collect = commands.add_parser("collect", help="roll out a behaviour policy into a Minari dataset")
    collect.add_argument("--env", default="Panda-v0", choices=list(envs.ENV_IDS))
    collect.add_argument("--policy", default="pid", help=f"one of {POLICIES} or the path of a saved SB3 model")
    collect.add_argument("--algo", default=None, help="the SB3/RL-Zoo3 algorithm of a model policy (sac, cql, ...)")
    collect.add_argument("--episodes", type=int, default=10_000)
    collect.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    collect.add_argument("--noise", type=float, default=None, help="std (rad) of noise on the executed arm targets")
    collect.add_argument("--action-mode", default=None, choices=["absolute", "delta"],
                         help="the env's action mode (default: absolute; a model policy's own)")  # fmt: skip
    collect.add_argument("--workers", type=int, default=1)
    collect.add_argument("--ray", metavar="ADDRESS", default=None,
                         help="run the episodes as Ray tasks on the cluster at ADDRESS (auto, host:port or "
                              "ray://host:port) instead of --workers processes: the same dataset")  # fmt: skip
    collect.add_argument("--dataset-id", default=None, help="default: sb3cql/<env>/<policy>[-delta]-v0")
    collect.add_argument("--overwrite", action="store_true",
                         help="replace an existing dataset of that id, and a partial collection of another spec")  # fmt: skip
    collect.add_argument("--write-every", type=int, default=WRITE_EVERY,
                         help="episodes written to disk at a time (%(default)s): the most a crash loses")  # fmt: skip

    mix = commands.add_parser("mix", help="combine existing datasets into a new one")
    mix.add_argument("--dataset-id", required=True, help="id of the combined dataset")
    mix.add_argument("sources", nargs="+", help="ids of the datasets to combine")
    mix.add_argument("--overwrite", action="store_true", help="replace an existing dataset of that id")

    info = commands.add_parser("info", help="print a dataset's metadata")
    info.add_argument("dataset_id")

    args = parser.parse_args(argv)
    try:
        _run(args)
    except KeyboardInterrupt as interrupt:
        if args.command == "mix":
            print(f"interrupted: {args.dataset_id} not written", file=sys.stderr)
        elif not getattr(interrupt, "said", False):  # collect says what it kept; info wrote nothing
            print("interrupted: nothing written", file=sys.stderr)
        raise SystemExit(exit_status(interrupt)) from None
    except (DatasetError, FileExistsError, ValueError, OSError, ClusterError, gymnasium.error.Error) as error:
        print(f"{PROG}: error: {' '.join(str(error).split())}", file=sys.stderr)
        raise SystemExit(2) from None


def _run(args: argparse.Namespace) -> None:
    if args.command == "collect":
        action_mode = args.action_mode
        if args.policy not in POLICIES:
            action_mode = model_action_mode(args.policy, args.algo, args.env, args.action_mode)
        action_mode = action_mode or "absolute"
        env_kwargs = {"action_mode": action_mode} if action_mode != "absolute" else {}
        spec = CollectionSpec(args.env, args.policy, args.episodes, args.seed, args.noise, env_kwargs, algo=args.algo)
        dataset = collect_dataset(spec, args.dataset_id, workers=args.workers, overwrite=args.overwrite,
                                  write_every=args.write_every, ray_address=args.ray)  # fmt: skip
        metadata = dataset.storage.metadata
        print(
            f"{metadata['dataset_id']}: {dataset.total_episodes} episodes, {dataset.total_steps} transitions, "
            f"success rate {metadata['success_rate']:.3f}, at {dataset_path(metadata['dataset_id'])}"
        )
    elif args.command == "mix":
        combined = mix_datasets(args.sources, args.dataset_id, overwrite=args.overwrite)
        print(f"{args.dataset_id}: {combined.total_episodes} episodes, {combined.total_steps} transitions")
    else:
        metadata = load_dataset(args.dataset_id).storage.metadata
        for key in ("observation_space", "action_space"):
            metadata[key] = str(metadata[key])
        print(json.dumps(metadata, indent=2, default=sorted))


if __name__ == "__main__":
    run_command(main)
