"""The results folder of the protocol: where each piece lives, and its records written atomically.

results/
  protocol.json                     the settings; a re-run with other settings is refused
  runs/seed<S>/<algo>/<env>_<N>/    the zoo's log folders (``-f runs/seed<S>``), one per training segment
  runs/seed<S>/tb/<algo>/<env>_<N>/ their TensorBoard logs (``-tb``)
  runs/seed<S>/<row>.log            the zoo's output, all segments
  runs/seed<S>/finetune/...         the same for the online fine-tuning runs (``-f runs/seed<S>/finetune``)
  records/train/<row>-seed<S>.json  one per finished training (or fine-tuning) run
  records/eval/<row>-seed<S>-<task>.json  one per finished final evaluation

A row is an algorithm, a PD controller, or an algorithm's runs fine-tuned online on a task (:data:`FINETUNE_ROW`).
  results.json, results.csv, table.md, figures/   the report, made again from the records
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
from importlib import metadata
from pathlib import Path
from typing import Any

from sb3_cql.files import write_atomically as write_text  # noqa: F401  (the records' writes: the package's one)
from sb3_cql.files import write_json  # noqa: F401

#: The row of an algorithm's runs fine-tuned online on a task: its best offline model, trained on with interaction.
FINETUNE_ROW = "{algo}-finetune-{task}"


def finetune_parts(row: str) -> tuple[str, str | None]:
    """``(algorithm, task)`` of a fine-tuned row (:data:`FINETUNE_ROW`), ``(row, None)`` of any other."""
    algo, separator, task = row.partition("-finetune-")
    return (algo, task) if separator else (row, None)


def read_json(path: Path) -> Any | None:
    """The JSON at ``path``, or ``None`` if there is none."""
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None


class ResultsFolder:
    """Paths of the protocol's results folder ``root`` (``--results-dir``; the module docstring has the layout)."""

    def __init__(self, root: Path | str) -> None:
        self.root = Path(root).resolve()

    @property
    def protocol(self) -> Path:
        return self.root / "protocol.json"

    def run_dir(self, seed: int) -> Path:
        """The zoo's ``-f`` folder of every algorithm trained with ``seed``."""
        return self.root / "runs" / f"seed{seed}"

    def training_log(self, algo: str, seed: int) -> Path:
        return self.run_dir(seed) / f"{algo}.log"

    def training_record(self, algo: str, seed: int) -> Path:
        return self.root / "records" / "train" / f"{algo}-seed{seed}.json"

    def evaluation_record(self, algo: str, seed: int, task: str) -> Path:
        return self.root / "records" / "eval" / f"{algo}-seed{seed}-{task}.json"

    def training_records(self) -> list[dict[str, Any]]:
        return [json.loads(path.read_text()) for path in sorted((self.root / "records" / "train").glob("*.json"))]

    def evaluation_records(self) -> list[dict[str, Any]]:
        return [json.loads(path.read_text()) for path in sorted((self.root / "records" / "eval").glob("*.json"))]

    @property
    def figures(self) -> Path:
        return self.root / "figures"


def system_info() -> dict[str, Any]:
    """Commit, hardware and versions, for the results: what a reader needs to compare figures across machines."""
    cpu_model = platform.processor() or None
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu_model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass

    def git(*words: str) -> str:
        return subprocess.run(["git", *words], cwd=Path(__file__).parent, capture_output=True, text=True, check=True).stdout

    try:
        commit, dirty = git("rev-parse", "HEAD").strip(), bool(git("status", "--porcelain", "--untracked-files=no").strip())
    except (OSError, subprocess.CalledProcessError):
        commit, dirty = None, None
    versions = {}
    for package in ("sb3-cql", "torch", "stable-baselines3", "rl-zoo3", "gymnasium", "pybullet", "minari", "numpy"):
        try:
            versions[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            versions[package] = None
    return {
        "commit": commit,
        "uncommitted_changes": dirty,
        "cpu_model": cpu_model,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "versions": versions,
    }
