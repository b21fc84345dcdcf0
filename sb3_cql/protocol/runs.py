"""One training run of the protocol as RL-Zoo3 leaves it on disk: its segments, stitched into one history.

A run (one algorithm, one seed) lives in a zoo log folder ``<run dir>/<algo>/``. Each zoo process makes a *segment*
``Panda-v0_<N>``: the first trains from scratch; a resumed one was started with ``-i <checkpoint>`` and restarts
the zoo's step count at 0, so its steps are offset by the checkpoint's. A later segment that resumed from global
step ``g`` discards whatever earlier segments did after ``g``: the run's history is everything up to each
segment's cut. A fine-tuning run's first segment starts (``-i``) from a model outside the run, at step 0.
Everything is read back from the zoo's own files, so a run killed at any moment is read correctly: an unreadable file
counts as absent.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

#: The zoo's names: the final model of a segment, its best model, its checkpoints.
FINAL_MODEL, BEST_MODEL, CHECKPOINT_GLOB = "{env_id}.zip", "best_model.zip", "rl_model_*_steps.zip"
#: Folder of a run dir holding each segment's TensorBoard logs: ``tb/<algo>/<env_id>_<N>`` (the zoo's ``-tb``).
TENSORBOARD_FOLDER = "tb"


def model_timesteps(path: Path) -> int | None:
    """``num_timesteps`` of the SB3 model saved at ``path``, read from its zip without torch; ``None`` if the file
    is missing or incomplete (a save interrupted by a kill)."""
    try:
        with zipfile.ZipFile(path) as archive:
            if archive.testzip() is not None:
                return None
            return int(json.loads(archive.read("data"))["num_timesteps"])
    except (OSError, KeyError, ValueError, zipfile.BadZipFile):
        return None


def checkpoint_timesteps(path: Path) -> int | None:
    """The step in the name of a zoo checkpoint ``rl_model_<N>_steps.zip``, else ``None``."""
    parts = path.stem.rsplit("_", 2)  # rl_model, <N>, steps
    return int(parts[1]) if len(parts) == 3 and parts[2] == "steps" and parts[1].isdigit() else None


def _load_yaml(path: Path) -> dict | None:
    try:
        return dict(yaml.unsafe_load(path.read_text()) or {})  # the zoo dumps OrderedDicts
    except (OSError, yaml.YAMLError):
        return None


@dataclass
class Segment:
    """One zoo process of a run, in its log folder ``<run dir>/<algo>/<env_id>_<N>`` (``number`` N), asked to make
    ``n_timesteps`` steps from global step ``offset`` (that of the checkpoint it ``resumed_from``, ``<segment
    folder>/<file>``), its history discarded by a later segment after global step ``cut`` (``None``: kept whole);
    ``env_kwargs``: its envs' keywords (the command line's, else the config's)."""

    folder: Path
    number: int
    n_timesteps: int
    offset: int = 0
    cut: int | None = None
    resumed_from: str | None = None
    env_kwargs: dict = field(default_factory=dict)

    def keeps(self, local_step: int) -> bool:
        """Whether this segment's step ``local_step`` belongs to the run's history."""
        return self.cut is None or self.offset + local_step <= self.cut

    def evaluations(self) -> tuple[np.ndarray, np.ndarray]:
        """Local timesteps and success rates of the kept evaluations (empty if the file is missing or unreadable)."""
        try:
            with np.load(self.folder / "evaluations.npz") as data:
                timesteps = data["timesteps"].astype(int)
                scores = data["successes"] if "successes" in data and data["successes"].size else data["results"]
                rates = np.asarray(scores, dtype=float).reshape(len(timesteps), -1).mean(axis=1)
        except (OSError, KeyError, ValueError, zipfile.BadZipFile):
            return np.zeros(0, dtype=int), np.zeros(0)
        kept = np.array([self.keeps(step) for step in timesteps], dtype=bool)
        return timesteps[kept], rates[kept]

    def models(self, env_id: str) -> list[tuple[int, Path]]:
        """Complete saved models of this segment in the run's history: (local step, path), oldest first."""
        paths = [self.folder / FINAL_MODEL.format(env_id=env_id), self.folder / BEST_MODEL]
        paths += sorted(self.folder.glob(CHECKPOINT_GLOB))
        found = [(model_timesteps(path), path) for path in paths if path.is_file()]
        return sorted((step, path) for step, path in found if step is not None and self.keeps(step))


@dataclass
class Run:
    """The stitched history of one zoo training run on ``env_id`` in ``log_folder`` (``<run dir>/<algo>``): its
    ``segments`` in order, offsets and cuts resolved."""

    log_folder: Path
    env_id: str
    segments: list[Segment] = field(default_factory=list)

    @classmethod
    def read(cls, log_folder: Path, env_id: str, outside_start: bool = False) -> Run:
        """Read every segment that got as far as writing its configuration (earlier deaths left nothing to use).
        ``outside_start``: the first segment continued a model from elsewhere (fine-tuning), and starts at step 0."""
        run = cls(log_folder, env_id)
        numbered = []
        for folder in log_folder.glob(f"{env_id}_*"):
            suffix = folder.name[len(env_id) + 1 :]
            if folder.is_dir() and suffix.isdigit():
                numbered.append((int(suffix), folder))
        by_name: dict[str, Segment] = {}
        for number, folder in sorted(numbered):
            args, config = _load_yaml(folder / env_id / "args.yml"), _load_yaml(folder / env_id / "config.yml")
            if args is None or config is None:
                continue
            n_timesteps = int(args["n_timesteps"]) if int(args.get("n_timesteps", -1)) > 0 else int(config["n_timesteps"])
            env_kwargs = dict(args.get("env_kwargs") or config.get("env_kwargs") or {})
            segment = Segment(folder, number, n_timesteps, env_kwargs=env_kwargs)
            source = args.get("trained_agent") or ""
            if source and not (outside_start and not run.segments):
                # The checkpoint's folder and file name only, so that a results folder can be moved.
                source_path = Path(source)
                parent = by_name.get(source_path.parent.name)
                model = log_folder / source_path.parent.name / source_path.name
                # A checkpoint no longer on disk (models are not kept with a results folder's records): its name's step.
                step = model_timesteps(model) if model.is_file() else checkpoint_timesteps(model)
                if parent is None or step is None:
                    raise RuntimeError(f"{folder} resumed from {source}, which is not a model of this run")
                segment.offset, segment.resumed_from = parent.offset + step, f"{source_path.parent.name}/{source_path.name}"
            for earlier in run.segments:  # a resumed segment discards what earlier ones did after its start
                earlier.cut = segment.offset if earlier.cut is None else min(earlier.cut, segment.offset)
            run.segments.append(segment)
            by_name[folder.name] = segment
        return run

    @property
    def n_timesteps(self) -> int | None:
        """The run's training budget (gradient or env steps): that of its first segment."""
        return self.segments[0].n_timesteps if self.segments else None

    @property
    def env_kwargs(self) -> dict:
        """Keywords of the run's envs (those of its first segment), which its models are evaluated with."""
        return self.segments[0].env_kwargs if self.segments else {}

    def latest_model(self) -> tuple[int, Path] | None:
        """The saved model furthest into the run's history (global step, path), to resume from."""
        candidates = [(seg.offset + step, path) for seg in self.segments for step, path in seg.models(self.env_id)]
        return max(candidates, key=lambda item: item[0]) if candidates else None

    def is_complete(self) -> bool:
        """Whether the history reaches the budget with a final model (a kill can also leave a final model)."""
        latest = self.latest_model()
        return latest is not None and self.n_timesteps is not None and latest[0] >= self.n_timesteps

    def evaluations(self) -> tuple[np.ndarray, np.ndarray]:
        """Global timesteps and success rates of every evaluation in the run's history, in order."""
        if not self.segments:
            return np.zeros(0, dtype=int), np.zeros(0)
        evaluations = [segment.evaluations() for segment in self.segments]
        steps = [local_steps + segment.offset for segment, (local_steps, _) in zip(self.segments, evaluations, strict=True)]
        return np.concatenate(steps), np.concatenate([rates for _, rates in evaluations])

    def tensorboard_folder(self, segment_name: str) -> Path:
        """Where the segment ``segment_name`` (``<env_id>_<N>``) writes TensorBoard logs: given to the zoo as ``-tb``."""
        return self.log_folder.parent / TENSORBOARD_FOLDER / self.log_folder.name / segment_name

    def scalars(self, tag: str) -> tuple[np.ndarray, np.ndarray]:
        """Global steps and values of the TensorBoard scalar ``tag`` (``train/actor_loss``, ...) in the history."""
        from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

        steps: list[int] = []
        values: list[float] = []
        for segment in self.segments:
            for events in sorted(self.tensorboard_folder(segment.folder.name).glob("**/events.out.tfevents.*")):
                accumulator = EventAccumulator(str(events), size_guidance={"scalars": 0}).Reload()
                if tag not in accumulator.Tags()["scalars"]:
                    continue
                for event in accumulator.Scalars(tag):
                    if segment.keeps(event.step):
                        steps.append(segment.offset + event.step)
                        values.append(event.value)
        return np.asarray(steps, dtype=int), np.asarray(values, dtype=float)

    def best_model(self) -> tuple[int, float | None, Path]:
        """The best evaluated model of the history: (global step, its evaluation success rate, path).

        EvalCallback's rule, across segments: the highest evaluation, the earliest on ties. Only models that were
        evaluated count (best models and checkpoints at evaluation steps); without evaluations, the latest model.
        """
        candidates = []
        for segment in self.segments:
            evaluated = dict(zip(*segment.evaluations(), strict=True))
            for step, path in segment.models(self.env_id):
                if step in evaluated:
                    candidates.append((-evaluated[step], segment.offset + step, path))
        if candidates:
            negative_rate, step, path = min(candidates, key=lambda item: (item[0], item[1]))
            return step, -negative_rate, path
        latest = self.latest_model()
        if latest is None:
            raise FileNotFoundError(f"no saved model in {self.log_folder}")
        return latest[0], None, latest[1]
