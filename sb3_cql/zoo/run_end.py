"""How a run of ours ends: where its models are and the commands to use them, or, cut short by Ctrl-C (which the zoo
swallows to save the model), what it kept, with the shell's status 130."""

from __future__ import annotations

import contextlib
import shlex
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from sb3_cql.processes import INTERRUPTED_STATUS, interrupts_noted


def run_commands(algo: str, env_id: str, save_path: Path) -> list[str]:
    """What to do with a run's models: evaluate on the three tasks, record a video (the zoo's own ``--exp-id``), each
    command quoted for the shell (a folder with a space is one word)."""
    log_folder, exp_id = save_path.parent.parent, save_path.name.rsplit("_", 1)[-1]
    model = save_path / ("best_model.zip" if (save_path / "best_model.zip").is_file() else f"{env_id}.zip")
    load_best = ["--load-best"] if model.name == "best_model.zip" else []
    evaluate = ["python", "-m", "sb3_cql.evaluate", str(model), "--algo", algo, "-n", "100"]
    record = ["python", "-m", "rl_zoo3.record_video", "--algo", algo, "--env", env_id, "-f", str(log_folder),
              "--exp-id", exp_id, *load_best, "-n", "700"]  # fmt: skip
    return [f"evaluate on the three tasks: {shlex.join(evaluate)}", f"record a video: {shlex.join(record)}"]


@contextlib.contextmanager
def ctrl_c_noted(manager: Any) -> Iterator[None]:
    """Note a Ctrl-C during the block in ``manager._sb3_cql_interrupted`` (the zoo's ``learn`` returns after one), to
    say after the zoo's save that the run was cut short; Ctrl-C still raises ``KeyboardInterrupt`` for the zoo."""
    manager._sb3_cql_interrupted = False
    with interrupts_noted() as noted:
        try:
            yield
        finally:
            manager._sb3_cql_interrupted = noted() == signal.SIGINT


def interrupted_before_training(removed: Path | None, kept: str) -> None:
    """End a run cut short before its first step, whose folder ``removed`` (if any) held no model."""
    gone = f", {removed} removed" if removed is not None else ""
    print(f"interrupted before training started: {kept}{gone}", file=sys.stderr)
    raise SystemExit(INTERRUPTED_STATUS) from None


def say_how_it_ended(manager: Any, model: Any) -> None:
    """After the zoo's save: the models and the commands to use them; or what Ctrl-C kept, ending with status 130."""
    folder, env_id = Path(manager.save_path), manager.env_name.gym_id
    best = (folder / "best_model.zip").is_file()
    if getattr(manager, "_sb3_cql_interrupted", False):
        kept = " and the best evaluated so far, best_model.zip," if best else ""
        print(f"interrupted at step {model.num_timesteps} of {manager.n_timesteps}: kept {folder / env_id}.zip (the model "
              f"at that step){kept} in {folder}")  # fmt: skip
        raise SystemExit(INTERRUPTED_STATUS)
    print(f"models: {folder / env_id}.zip (last)" + (f", {folder / 'best_model.zip'} (best evaluated)" if best else ""))
    for line in run_commands(manager.algo, env_id, folder):
        print(line)
