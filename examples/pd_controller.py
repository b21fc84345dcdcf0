"""Run the scripted PD controller on grasping tasks: print its success rates and save videos.

    python examples/pd_controller.py --env Panda-v0 --n-episodes 100 --video-folder videos
    python examples/pd_controller.py --env Panda-v0 PandaForce-v0 --n-episodes 5 --video-folder videos
    python examples/pd_controller.py --env PandaForce-v0 --regrasp --video-folder videos   # grasps a lost object again

Headless: frames come from PyBullet's software renderer, so no display is needed.
"""

from __future__ import annotations

import argparse

import gymnasium as gym
import numpy as np
from gymnasium.wrappers import RecordVideo
from tqdm import tqdm

import envs


def evaluate_pd_controller(
    env_id: str,
    n_episodes: int,
    seed: int = 0,
    action_mode: str = "absolute",
    video_folder: str | None = None,
    n_videos: int = 1,
    regrasp: bool = False,
) -> list[bool]:
    """Run the PD controller for ``n_episodes`` episodes (episode ``i`` reset with ``seed + i``) and return
    the success of each; with ``video_folder``, the first ``n_videos`` episodes are saved as MP4 there. With
    ``regrasp``, the controller reopens and grasps again when it has lost the object."""
    env = gym.make(env_id, action_mode=action_mode, render_mode="rgb_array" if video_folder else None)
    if video_folder:
        env = RecordVideo(env, video_folder, episode_trigger=lambda episode: episode < n_videos, name_prefix=f"pd-{env_id}")
    controller = envs.PDController.for_env(env, regrasp=regrasp)
    successes = []
    with tqdm(range(n_episodes), desc=f"PD on {env_id}", unit="episode") as episodes:
        for episode in episodes:
            observation, _ = env.reset(seed=seed + episode)
            done = False
            while not done:
                action, _ = controller.predict(observation)
                observation, _, terminated, truncated, info = env.step(action)
                done = terminated or truncated
            successes.append(bool(info["is_success"]))
            episodes.set_postfix(success_rate=f"{np.mean(successes):.3f}")
    env.close()
    controller.close()
    return successes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", nargs="+", default=["Panda-v0"], choices=list(envs.ENV_IDS), help="one or more env ids")
    parser.add_argument("--n-episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0, help="episode i is reset with seed + i")
    parser.add_argument("--action-mode", default="absolute", choices=["absolute", "delta"])
    parser.add_argument("--video-folder", default=None, help="save the first episodes as MP4 here")
    parser.add_argument("--n-videos", type=int, default=1)
    parser.add_argument("--regrasp", action="store_true", help="the controller that grasps a lost object again")
    args = parser.parse_args()
    for env_id in args.env:
        successes = evaluate_pd_controller(
            env_id, args.n_episodes, args.seed, args.action_mode, args.video_folder, args.n_videos, args.regrasp
        )
        rate = np.mean(successes)
        name = "regrasping PD controller" if args.regrasp else "PD controller"
        print(f"{name} on {env_id} ({args.action_mode}): success rate {rate:.3f} over {len(successes)} episodes")
    if args.video_folder:
        print(f"video(s) saved in {args.video_folder}/")


if __name__ == "__main__":
    main()
