"""The protocol's units of work, each recorded on disk when done: train an algorithm with one seed (RL-Zoo3 in a
subprocess, resumed from its last checkpoint after a kill), fine-tune its best model online on a task (the same way),
evaluate a policy on one task."""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import yaml

import envs
from sb3_cql.processes import child_command
from sb3_cql.protocol.records import FINETUNE_ROW, ResultsFolder, finetune_parts, read_json, write_json
from sb3_cql.protocol.runs import Run

#: The task every algorithm trains on (thesis 4.3); the final evaluation covers all of ``envs.ENV_IDS``.
TRAIN_ENV = "Panda-v0"
#: The thesis's five seeds.
THESIS_SEEDS = (117, 12321, 7456, 3426, 573)
#: The scripted PD controllers (``envs.CONTROLLERS``): evaluated, never trained.
SCRIPTED = tuple(envs.CONTROLLERS)
#: Rows of the thesis's Table 5.1, BC, and the regrasping PD controller (the other scripted rows on request).
DEFAULT_ALGOS = ("cql", "bc", "pid", "pid-regrasp", "sac")
#: Lines of a failed zoo run's log shown in the error.
LOG_TAIL_LINES = 40
#: The zoo config of the fine-tuning runs (in our hyperparams/).
FINETUNE_CONFIG = "cql_finetune.yml"


def fine_tunes(algo: str) -> bool:
    """Whether the zoo algorithm ``algo`` fine-tunes online after offline training (it takes ``online_fraction``)."""
    from rl_zoo3.utils import ALGOS

    known = getattr(ALGOS.get(algo), "known_keywords", None)  # our offline algorithms' keywords, theirs and SAC's
    return known is not None and "online_fraction" in known()


class ProtocolError(RuntimeError):
    """A unit of the protocol failed, or the request cannot be run (unknown algorithm, other settings on disk)."""


class UnitsFailed(ProtocolError):
    """Some units failed; the others are done and recorded."""


@dataclass
class Settings:
    """What a results folder's numbers depend on: a re-run must use the same (:meth:`check_folder`). The options of
    ``python -m sb3_cql.protocol`` of the same names; ``None``: each algorithm's config. ``zoo_args`` are the offline
    trainings' extra ``rl_zoo3.train`` arguments, ``finetune_args`` the fine-tuning runs' (a fine-tuned model keeps
    the former's settings); ``dataset`` replaces the ``dataset`` of every offline algorithm's config."""

    n_timesteps: int | None = None
    eval_freq: int | None = None
    eval_episodes: int | None = None
    episodes: int = 100
    zoo_args: list[str] = field(default_factory=list)
    dataset: str | None = None
    finetune_args: list[str] = field(default_factory=list)

    def dataset_args(self, config_dataset: str | None) -> list[str]:
        """The zoo arguments with ``dataset`` in place of ``config_dataset`` (an online algorithm's ``None`` stays), in
        their own ``--hyperparams`` if they have one (a second flag would replace it)."""
        if self.dataset is None or config_dataset is None:
            return list(self.zoo_args)
        item = f"dataset:{self.dataset!r}"
        if "--hyperparams" in self.zoo_args:
            at = self.zoo_args.index("--hyperparams") + 1
            return [*self.zoo_args[:at], item, *self.zoo_args[at:]]
        return [*self.zoo_args, "--hyperparams", item]

    def check_folder(self, results: ResultsFolder) -> None:
        """Record these settings in a new results folder, or check they are those of an existing one."""
        recorded = read_json(results.protocol)
        if recorded is None:
            write_json(results.protocol, {"settings": asdict(self), "train_env": TRAIN_ENV})
        elif {**asdict(Settings()), **recorded["settings"]} != asdict(self):  # settings added since: their defaults
            raise ProtocolError(
                f"{results.root} holds results made with other settings ({recorded['settings']}, not {asdict(self)}): "
                "use another --results-dir, or the same options"
            )


@dataclass
class Protocol:
    """The whole protocol: which algorithms (RL-Zoo3 names, and :data:`SCRIPTED`'s) and seeds, evaluated on which
    tasks, where, with how many workers (each zoo process gets one torch thread when there are several) or on the
    Ray cluster at ``ray_address``; ``save_freq``: steps between checkpoints, where a killed training resumes;
    ``finetune``: tasks on which each seed's best model of every algorithm that fine-tunes is fine-tuned online
    (``hyperparams/cql_finetune.yml``), each a row of its own (:data:`FINETUNE_ROW`)."""

    results: ResultsFolder
    algos: list[str]
    seeds: list[int]
    tasks: list[str]
    settings: Settings
    save_freq: int = 10_000
    workers: int = 1
    finetune: list[str] = field(default_factory=list)
    ray_address: str | None = None

    def check(self) -> None:
        """Clear errors before any work: unknown algorithms or tasks, a zoo without our config for an algorithm."""
        from rl_zoo3.utils import ALGOS

        from sb3_cql.zoo.plugin import config_file

        self._check_numbers()
        self._check_results_folder()
        unknown_tasks = sorted((set(self.tasks) | set(self.finetune)) - set(envs.ENV_IDS))
        if unknown_tasks:
            raise ProtocolError(f"unknown task(s) {unknown_tasks}: choose among {list(envs.ENV_IDS)}")
        if self.finetune and not any(fine_tunes(algo) for algo in self.algos):
            raise ProtocolError(f"--finetune {' '.join(self.finetune)}: none of --algos {' '.join(self.algos)} fine-tunes "
                                 "online (cql does)")  # fmt: skip
        own_config = any(arg.startswith(("--conf-file", "-conf")) for arg in self.settings.zoo_args)
        for algo in self.algos:
            if algo in SCRIPTED:
                continue
            if algo not in ALGOS:
                raise ProtocolError(f"unknown algo {algo!r}: one of {sorted([*ALGOS, *SCRIPTED])}")
            if not own_config and config_file(algo, TRAIN_ENV) is None:
                raise ProtocolError(f"hyperparams/{algo}.yml has no {TRAIN_ENV} entry: add one, or give --conf-file")
            if not own_config:
                _check_dataset(self._dataset_id(algo, config_file(algo, TRAIN_ENV)))

    def _check_numbers(self) -> None:
        """Every count the protocol is given is one it can run with."""
        settings = self.settings
        counts = {"--workers": self.workers, "--episodes": settings.episodes, "--save-freq": self.save_freq,
                  "--n-timesteps": settings.n_timesteps, "--eval-freq": settings.eval_freq,
                  "--eval-episodes": settings.eval_episodes}  # fmt: skip
        for option, value in counts.items():
            if value is not None and (not isinstance(value, int) or isinstance(value, bool) or value < 1):
                raise ProtocolError(f"{option} must be an integer >= 1, got {value!r}")
        if not self.seeds:
            raise ProtocolError("--seeds: give at least one seed")
        lists = {"--algos": self.algos, "--seeds": self.seeds, "--tasks": self.tasks, "--finetune": self.finetune}
        for option, values in lists.items():  # a repeat would run a unit twice, or two runs into one folder
            repeated = next((value for value, count in Counter(values).items() if count > 1), None)
            if repeated is not None:
                raise ProtocolError(f"{option} {' '.join(map(str, values))}: {repeated} is given more than once; give each "
                                    "once")  # fmt: skip
        for seed in self.seeds:
            if not isinstance(seed, int) or seed < 0:
                raise ProtocolError(f"--seeds must be integers >= 0, got {seed!r}")

    def _check_results_folder(self) -> None:
        """The results folder is (or can be made) a folder this user may write in; a ``--ray`` cluster answers."""
        root = self.results.root
        if root.exists() and not root.is_dir():
            raise ProtocolError(f"--results-dir {root} is a file: give a folder")
        existing = root
        while not existing.exists():
            existing = existing.parent
        if not existing.is_dir() or not os.access(existing, os.W_OK | os.X_OK):
            raise ProtocolError(f"--results-dir {root} cannot be written: {existing} is not a folder this user may "
                                 "write in; give another --results-dir")  # fmt: skip
        if self.ray_address is not None:
            from sb3_cql.cluster import ClusterError, connect

            try:
                connect(self.ray_address)
            except ClusterError as error:
                raise ProtocolError(str(error)) from None

    def _dataset_id(self, algo: str, config: Path) -> str | None:
        """The dataset ``algo`` trains on: its config's ``dataset`` for :data:`TRAIN_ENV`, or the one ``--dataset`` or a
        ``--hyperparams dataset:...`` item of the zoo arguments gives (evaluated as the zoo evaluates it)."""
        dataset = config_dataset(config)
        for item in self.settings.dataset_args(dataset):
            key, _, value = item.partition(":")
            if key == "dataset" and value:
                try:
                    dataset = eval(value)  # the zoo's own StoreDict does the same with the item
                except Exception:
                    raise ProtocolError(f"--zoo-args: {item!r} is not dataset:\"'ID'\" (a quoted string)") from None
        return dataset if isinstance(dataset, str) else None


def config_dataset(config: Path) -> str | None:
    """The ``dataset`` of a zoo config's :data:`TRAIN_ENV` entry (``None``: an online algorithm)."""
    dataset = (yaml.safe_load(config.read_text()) or {}).get(TRAIN_ENV, {}).get("dataset")
    return dataset if isinstance(dataset, str) else None


def _check_dataset(dataset_id: str | None) -> None:
    """A dataset a training needs exists, or is a standard one that the training collects first."""
    from sb3_cql.data import DatasetError, load_dataset
    from sb3_cql.data.collection import standard_collection
    from sb3_cql.data.ids import dataset_exists

    if dataset_id is None or dataset_exists(dataset_id) or standard_collection(dataset_id) is not None:
        return  # there, or collected on the first run (sb3_cql.data.ensure_dataset)
    try:
        load_dataset(dataset_id)
    except DatasetError as error:
        raise ProtocolError(str(error)) from None


def _log_tail(path: Path, lines: int = LOG_TAIL_LINES) -> str:
    """The last ``lines`` lines of a zoo log, without PyBullet's ``argv[0]=`` noise."""
    text = path.read_text(errors="replace").splitlines() if path.is_file() else []
    return "\n".join([line for line in text if not line.startswith("argv[0]=")][-lines:])


def train(protocol: Protocol, algo: str, seed: int, threads: int | None, task: str | None = None) -> dict[str, Any]:
    """Train ``algo`` on :data:`TRAIN_ENV` with ``seed`` through ``python -m rl_zoo3.train``, continuing the run on
    disk from its latest saved model (``-i``, ``-n`` the steps left); record and return the result. With ``task``,
    fine-tune that training's recorded best model online on ``task`` instead (the row :data:`FINETUNE_ROW`).

    :raises ProtocolError: if a zoo process fails (with the tail of its log) or makes no progress.
    """
    results, settings = protocol.results, protocol.settings
    env_id, row = task or TRAIN_ENV, algo if task is None else FINETUNE_ROW.format(algo=algo, task=task)
    zoo_folder = results.run_dir(seed) if task is None else results.run_dir(seed) / "finetune"
    log, start_model = results.training_log(row, seed), None
    if task is not None:
        offline = read_json(results.training_record(algo, seed))
        if offline is None:
            raise ProtocolError(f"{algo} seed {seed} is not trained yet: it has no model to fine-tune")
        start_model = results.root / offline["best_model"]
    label = f"finetune {algo} seed {seed} {task}" if task else f"train {algo} seed {seed}"
    print(f"[{label}] started", flush=True)
    log_folder = zoo_folder / algo
    log_folder.mkdir(parents=True, exist_ok=True)
    times_path = log_folder / f"segment_times{'' if task is None else '_' + task}.json"
    times: dict[str, list[float]] = read_json(times_path) or {}
    from rl_zoo3.utils import get_latest_run_id

    from sb3_cql.zoo.plugin import hyperparams_dir

    run = Run.read(log_folder, env_id, outside_start=task is not None)
    while not run.is_complete():
        segment = f"{env_id}_{get_latest_run_id(str(log_folder), env_id) + 1}"  # the folder the zoo will make
        command = [sys.executable, "-m", "rl_zoo3.train", "--algo", algo, "--env", env_id, "--seed", str(seed),
                   "-f", str(zoo_folder), "-tb", str(run.tensorboard_folder(segment)),
                   "--save-freq", str(protocol.save_freq)]  # fmt: skip
        if threads is not None:
            command += ["--num-threads", str(threads)]
        if settings.eval_freq is not None:
            command += ["--eval-freq", str(settings.eval_freq)]
        if settings.eval_episodes is not None:
            command += ["--eval-episodes", str(settings.eval_episodes)]
        latest = run.latest_model()
        if latest is None:
            if start_model is not None:
                command += ["-i", str(start_model)]
            if settings.n_timesteps is not None:
                command += ["-n", str(settings.n_timesteps)]
        else:
            assert run.n_timesteps is not None
            command += ["-i", str(latest[1]), "-n", str(run.n_timesteps - latest[0])]
        if task is None:
            command += settings.dataset_args(_config_dataset(algo, settings))
        else:
            command += ["--conf-file", str(hyperparams_dir() / FINETUNE_CONFIG), *settings.finetune_args]
        start = time.time()
        times[segment] = [start, start]
        write_json(times_path, times)
        with open(log, "a") as file:
            file.write(f"\n=== {time.strftime('%Y-%m-%d %H:%M:%S')} segment {segment}: {shlex.join(command)}\n")
            file.flush()
            # The zoo takes Ctrl-C as it does (saving the model at that step), and dies with its worker.
            returncode = subprocess.run(command, stdout=file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                        preexec_fn=child_command()).returncode  # fmt: skip
        times[segment] = [start, time.time()]
        write_json(times_path, times)
        if returncode != 0:
            raise ProtocolError(f"{label}: the zoo failed (exit {returncode}); end of {log}:\n{_log_tail(log)}")
        run = Run.read(log_folder, env_id, outside_start=task is not None)
        progress = run.latest_model()
        if progress is None or (latest is not None and progress[0] <= latest[0]):
            raise ProtocolError(f"{label}: segment {segment} saved no progress; end of {log}:\n{_log_tail(log)}")
    best_step, best_rate, best_path = run.best_model()
    segments = [{"folder": s.folder.name, "offset": s.offset, "cut": s.cut, "resumed_from": s.resumed_from}
                for s in run.segments]  # fmt: skip
    record = {"algo": row, "seed": seed, "train_env": env_id, "log_folder": str(log_folder.relative_to(results.root)),
              "started_from": None if start_model is None else str(start_model.relative_to(results.root)),
              "training_steps": run.n_timesteps, "n_timesteps_override": settings.n_timesteps, "best_step": best_step,
              "best_eval_success_rate": best_rate, "best_model": str(best_path.relative_to(results.root)),
              "env_kwargs": run.env_kwargs, "segments": segments,
              "train_wall_time_s": round(_wall_time(run, times), 1)}  # fmt: skip
    write_json(results.training_record(row, seed), record)
    return record


def _config_dataset(algo: str, settings: Settings) -> str | None:
    """The dataset of ``algo``'s config in our hyperparams/ (``None`` with a ``--conf-file`` of the zoo arguments)."""
    from sb3_cql.zoo.plugin import config_file

    if any(arg.startswith(("--conf-file", "-conf")) for arg in settings.zoo_args):
        return None
    config = config_file(algo, TRAIN_ENV)
    return None if config is None else config_dataset(config)


def _wall_time(run: Run, times: dict[str, list[float]]) -> float:
    """Seconds spent in the run's segments: as timed by the runner, or up to a killed segment's last file."""
    total = 0.0
    for segment in run.segments:
        start, end = times.get(segment.folder.name, (None, None))
        if start is None:
            continue
        if end == start:  # killed along with the runner: until its last write
            end = max((path.stat().st_mtime for path in segment.folder.rglob("*")), default=start)
        total += end - start
    return total


def evaluate(protocol: Protocol, algo: str, seed: int, task: str, threads: int | None) -> dict[str, Any]:
    """Success rate of ``algo``'s best model of ``seed`` (or the PD controller; ``algo`` may be a fine-tuned row) over
    the final evaluation's episodes of ``task``, seeded with ``seed``; record and return it."""
    from sb3_cql.evaluate import load_policy, success_rate

    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    results, settings = protocol.results, protocol.settings
    training = None if algo in SCRIPTED else read_json(results.training_record(algo, seed))
    if algo not in SCRIPTED and training is None:
        raise ProtocolError(f"{algo} seed {seed} is not trained yet")
    start = time.time()
    if training is None:  # a PD controller, in the tasks' default (absolute) action mode
        policy, env_kwargs = load_policy(algo, None, task), {}
    else:  # in the envs it was trained in (its action mode)
        model = str(results.root / training["best_model"])
        policy, env_kwargs = load_policy(model, finetune_parts(algo)[0], task), training["env_kwargs"]
    rate = success_rate(policy, task, settings.episodes, seed, env_kwargs=env_kwargs)
    trained = {key: training and training[key] for key in ("best_step", "training_steps", "train_wall_time_s")}
    record = {"algo": algo, "seed": seed, "task": task, "success_rate": rate, "episodes": settings.episodes, **trained,
              "eval_wall_time_s": round(time.time() - start, 1)}  # fmt: skip
    write_json(results.evaluation_record(algo, seed, task), record)
    return record
