"""Fine-tune a model through the zoo's ``-i`` for a total of env steps, continuing from the last checkpoint after a
kill: each start is a segment (a zoo run folder under OUT), the first from MODEL, the next ones from the previous
segment's last checkpoint (its online transitions beside it) for the steps left. The final model is the last
segment's ``<ENV>.zip``, copied to ``OUT/final.zip`` when the total is reached.

    python research/scripts/finetune_resumable.py MODEL OUT --algo iql --env PandaForce-v0 --seed 1 \\
        --conf-file hyperparams/iql_finetune.yml --steps 100000 [--save-freq 10000] [--eval-freq 10000]

A resumed segment starts the random streams afresh (as a zoo run with ``-i`` does), so a run killed and resumed is
not the same, step for step, as one that was not. One run at a time holds OUT: a second start on the same OUT while
the first runs is refused in one line (two would each count the other's segment as done).
"""

from __future__ import annotations

import argparse
import fcntl
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path


def checkpoints(segment: Path) -> list[tuple[int, Path]]:
    """``(steps, path)`` of a segment's checkpoints that have their replay buffer beside them, by steps."""
    found = []
    for path in segment.glob("rl_model_*_steps.zip"):
        steps = int(re.fullmatch(r"rl_model_(\d+)_steps\.zip", path.name).group(1))
        if (segment / f"rl_model_replay_buffer_{steps}_steps.pkl").is_file():
            found.append((steps, path))
    return sorted(found)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python research/scripts/finetune_resumable.py", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("model", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--algo", default="iql")
    parser.add_argument("--env", default="PandaForce-v0")
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--conf-file", default="hyperparams/iql_finetune.yml")
    parser.add_argument("--steps", type=int, default=100_000, help="a multiple of --save-freq")
    parser.add_argument("--save-freq", type=int, default=10_000)
    parser.add_argument("--eval-freq", type=int, default=10_000)
    parser.add_argument("--research-variants", action="store_true",
                        help="train with research/zoo_train.py (--algo may name a research variant: iql_capped)")  # fmt: skip
    args = parser.parse_args(argv)
    if args.steps % args.save_freq:
        parser.error("--steps must be a multiple of --save-freq: a segment's steps are counted by its checkpoints")
    args.out.mkdir(parents=True, exist_ok=True)
    lock = open(args.out / ".lock", "w")  # noqa: SIM115 - held until the process ends
    try:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        print(f"{args.out} is being fine-tuned by another process; wait for it or stop it first", file=sys.stderr)
        return 2
    while True:
        done, start = 0, args.model
        for segment in sorted((args.out / args.algo).glob(f"{args.env}_*"), key=lambda path: int(path.name.rsplit("_")[-1])):
            kept = checkpoints(segment)
            if kept:
                done, start = done + kept[-1][0], kept[-1][1]
        if done >= args.steps:
            shutil.copyfile(start, args.out / "final.zip.tmp")
            os.replace(args.out / "final.zip.tmp", args.out / "final.zip")
            print(f"{args.out}: {done} steps done; final model {args.out / 'final.zip'} ({start})", flush=True)
            return 0
        print(f"{args.out}: {done} steps done, {args.steps - done} left, from {start}", flush=True)
        research_trainer = [str(Path(__file__).resolve().parents[1] / "zoo_train.py")]
        trainer = research_trainer if args.research_variants else ["-m", "rl_zoo3.train"]
        command = [sys.executable, *trainer, "--algo", args.algo, "--env", args.env, "-i", str(start),
                   "--conf-file", args.conf_file, "--seed", str(args.seed), "--num-threads", "1", "-f", str(args.out),
                   "-n", str(args.steps - done), "--save-freq", str(args.save_freq),
                   "--eval-freq", str(args.eval_freq)]  # fmt: skip
        if subprocess.run(command).returncode != 0:
            return 1


if __name__ == "__main__":
    sys.exit(main())
