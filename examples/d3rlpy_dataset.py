"""Train d3rlpy on one of our Minari datasets, without sb3_cql: the datasets are plain Minari (HDF5) datasets.

Runs in a fresh environment with only d3rlpy and Minari (install torch first, or pip fetches a large CUDA build)::

    pip install torch==2.13.0 && pip install d3rlpy "minari[hdf5]" pillow

``pillow`` is needed although ``minari[hdf5]`` does not pull it in: minari 0.5.4's HDF5 storage imports PIL, so
``minari.load_dataset`` fails with ``ModuleNotFoundError: No module named 'PIL'`` without it. Usage::

    MINARI_DATASETS_PATH=/path/to/datasets python examples/d3rlpy_dataset.py sb3cql/Panda-v0/noisy-regrasp-delta-v0

Each Minari episode holds one more observation than actions (the final one); d3rlpy's ``MDPDataset`` takes one
observation per action and marks each episode's end with ``terminals`` (the task ended) or ``timeouts`` (time limit),
so the final observation is dropped (d3rlpy uses no next observation after a terminal, and skips the last transition
of a timed-out episode). The script trains d3rlpy's continuous behaviour cloning (``BCConfig``) for ``--steps``
gradient steps and prints its loss.

The tasks themselves are not needed and not made here: ``dataset.recover_environment()`` imports the entry point the
dataset stores (``envs.panda_env:PandaGraspEnv``), so in this environment it fails with ``ModuleNotFoundError: No
module named 'envs'``. It works after ``pip install pybullet`` with the sb3-cql repository's root on ``PYTHONPATH``
(the ``envs`` package needs only pybullet, numpy and gymnasium; sb3_cql itself is not imported).
"""

from __future__ import annotations

import argparse

import d3rlpy
import minari
import numpy as np


def to_mdp_dataset(dataset: minari.MinariDataset) -> d3rlpy.dataset.MDPDataset:
    """One d3rlpy transition per Minari step: the final observation of each episode is dropped."""
    observations, actions, rewards, terminals, timeouts = [], [], [], [], []
    for episode in dataset.iterate_episodes():
        terminated = np.asarray(episode.terminations, dtype=bool)
        # d3rlpy needs every episode to end in exactly one flag: a terminal wins over a timeout on the same step,
        # and an episode that ended in neither (cut short) counts as timed out.
        truncated = np.asarray(episode.truncations, dtype=bool) & ~terminated
        truncated[-1] |= not terminated[-1]
        observations.append(episode.observations[:-1])
        actions.append(episode.actions)
        rewards.append(episode.rewards)
        terminals.append(terminated)
        timeouts.append(truncated)
    return d3rlpy.dataset.MDPDataset(
        observations=np.concatenate(observations).astype(np.float32),
        actions=np.concatenate(actions).astype(np.float32),
        rewards=np.concatenate(rewards).astype(np.float32),
        terminals=np.concatenate(terminals).astype(np.float32),
        timeouts=np.concatenate(timeouts).astype(np.float32),
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("dataset_id", help="a local Minari dataset, e.g. sb3cql/Panda-v0/noisy-regrasp-delta-v0")
    parser.add_argument("--steps", type=int, default=100, help="gradient steps of behaviour cloning")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    d3rlpy.seed(args.seed)

    minari_dataset = minari.load_dataset(args.dataset_id)
    dataset = to_mdp_dataset(minari_dataset)
    print(
        f"{args.dataset_id}: {dataset.size()} episodes, {dataset.transition_count} transitions "
        f"(of {minari_dataset.total_steps} steps), observation shape {dataset.dataset_info.observation_signature.shape[0]}, "
        f"action size {dataset.dataset_info.action_size}"
    )

    bc = d3rlpy.algos.BCConfig().create(device="cpu:0")
    results = bc.fit(
        dataset,
        n_steps=args.steps,
        n_steps_per_epoch=args.steps,
        logger_adapter=d3rlpy.logging.NoopAdapterFactory(),
        show_progress=False,
    )
    _, metrics = results[-1]
    print(f"BC: {args.steps} steps, loss {metrics['loss']:.4f}")


if __name__ == "__main__":
    main()
