"""The protocol's numbers from its records: ``results.json``, ``results.csv`` and ``table.md`` (thesis Table 5.1:
mean ± standard deviation over seeds, and the interquartile mean with 95% stratified-bootstrap confidence
intervals from rliable; for fine-tuned rows, each run's start, early dip and best evaluation)."""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable
from typing import Any

import numpy as np

from sb3_cql.protocol.records import ResultsFolder, finetune_parts, read_json, write_json, write_text
from sb3_cql.protocol.runs import Run

#: Rows of the table in the thesis's order (then any other algorithm), and how they are printed.
ROW_ORDER = ("cql", "iql", "bc", "pid", "pid-regrasp", "pid-regrasp-yaw", "pid-regrasp-aligned", "sac")
#: The share of a fine-tuning run's env steps in which its early dip is looked for.
EARLY_SHARE = 0.2
#: Bootstrap resamples of the interval estimates; the generator's seed, so a report is made again identically.
BOOTSTRAP_REPS, BOOTSTRAP_SEED = 2000, 0
#: Columns of ``results.csv``: one row per final evaluation, with the run and the machine.
CSV_COLUMNS = ("algo", "seed", "task", "success_rate", "episodes", "best_step", "training_steps", "train_wall_time_s",
               "eval_wall_time_s", "commit", "cpu_model", "cpu_count", "torch", "stable-baselines3")  # fmt: skip


def algo_rank(algo: str) -> tuple[int, int, str]:
    """Sort key of the table's rows: a fine-tuned row right after its algorithm's."""
    base, task = finetune_parts(algo)
    return (ROW_ORDER.index(base) if base in ROW_ORDER else len(ROW_ORDER), task is not None, algo)


def row_label(algo: str) -> str:
    """How a row is printed: ``CQL``, ``CQL + online on PandaForce-v0``."""
    base, task = finetune_parts(algo)
    return base.upper() if task is None else f"{base.upper()} + online on {task}"


def algo_order(algos: Iterable[str]) -> list[str]:
    """``algos`` in the table's order."""
    return sorted(set(algos), key=algo_rank)


def success_matrix(evaluations: list[dict[str, Any]], tasks: list[str]) -> dict[str, tuple[list[int], np.ndarray]]:
    """Per algorithm, the seeds evaluated on every task in ``tasks`` and their success rates (seeds x tasks)."""
    rates: dict[str, dict[int, dict[str, float]]] = {}
    for record in evaluations:
        rates.setdefault(record["algo"], {}).setdefault(record["seed"], {})[record["task"]] = record["success_rate"]
    matrices = {}
    for algo in algo_order(rates):
        seeds = sorted(seed for seed, by_task in rates[algo].items() if all(task in by_task for task in tasks))
        if seeds:
            matrices[algo] = (seeds, np.array([[rates[algo][seed][task] for task in tasks] for seed in seeds]))
    return matrices


def summarise(matrices: dict[str, tuple[list[int], np.ndarray]], tasks: list[str]) -> dict[str, dict[str, Any]]:
    """Mean, standard deviation (n - 1, as the thesis's table), IQM and its 95% CI per algorithm and task."""
    from rliable import library as rly
    from rliable import metrics

    def iqm_per_task(scores: np.ndarray) -> np.ndarray:
        return np.array([metrics.aggregate_iqm(scores[:, column]) for column in range(scores.shape[1])])

    iqm, intervals = {}, {}
    for algo, (_, matrix) in matrices.items():  # seeded each: a row's interval depends on its own scores alone
        # rliable's StratifiedBootstrap draws its resamples from numpy's global generator (np.random.choice), not the
        # random_state it is given: seed that, and give the caller's state back.
        global_state = np.random.get_state()
        np.random.seed(BOOTSTRAP_SEED)
        try:
            estimates = rly.get_interval_estimates({algo: matrix}, iqm_per_task, reps=BOOTSTRAP_REPS)
        finally:
            np.random.set_state(global_state)
        iqm[algo], intervals[algo] = estimates[0][algo], estimates[1][algo]
    summary: dict[str, dict[str, Any]] = {}
    for algo, (seeds, matrix) in matrices.items():
        std = matrix.std(axis=0, ddof=1) if len(seeds) > 1 else np.full(len(tasks), np.nan)
        summary[algo] = {
            task: {
                "mean": float(matrix[:, column].mean()),
                "std": None if np.isnan(std[column]) else float(std[column]),
                "iqm": float(iqm[algo][column]),
                "iqm_ci95": [float(intervals[algo][0, column]), float(intervals[algo][1, column])],
                "seeds": seeds,
            }
            for column, task in enumerate(tasks)
        }
    return summary


def markdown_table(summary: dict[str, dict[str, Any]], tasks: list[str], episodes: int) -> str:
    """Table 5.1 (mean ± std over seeds) and the IQM table, best mean of each task in bold."""
    best = {task: max((summary[algo][task]["mean"] for algo in summary), default=None) for task in tasks}
    header = "| | " + " | ".join(tasks) + " |\n|---|" + "---|" * len(tasks) + "\n"
    seeds = sorted({len(summary[algo][task]["seeds"]) for algo in summary for task in tasks})
    lines = [
        f"Success rate of the best model of each run (PID: the thesis's PD controller; PID-REGRASP: ours, whose noisy "
        f"runs are the data) over {episodes} episodes per task, mean ± standard deviation over seeds (seeds per row: "
        f"{'/'.join(map(str, seeds)) or 0}).",
        "",
        header.rstrip("\n"),
    ]
    for algo in summary:
        cells = []
        for task in tasks:
            entry = summary[algo][task]
            std = "n/a" if entry["std"] is None else f"{entry['std']:.3f}"
            cell = f"{entry['mean']:.3f} ± {std}"
            cells.append(f"**{cell}**" if entry["mean"] == best[task] else cell)
        lines.append(f"| {row_label(algo)} | " + " | ".join(cells) + " |")
    if any(finetune_parts(algo)[1] for algo in summary):
        lines += ["", "Rows \"+ online on TASK\": each seed's best model of the algorithm fine-tuned online with "
                  "interaction with TASK (hyperparams/cql_finetune.yml), then scored like the others: on TASK they have "
                  "trained on the task they are scored on."]  # fmt: skip
    lines += ["", f"Interquartile mean over seeds [95% stratified-bootstrap confidence interval, {BOOTSTRAP_REPS} resamples, "
              "rliable].", "", header.rstrip("\n")]  # fmt: skip
    for algo in summary:
        entries = [summary[algo][task] for task in tasks]
        cells = [f"{entry['iqm']:.3f} [{entry['iqm_ci95'][0]:.3f}, {entry['iqm_ci95'][1]:.3f}]" for entry in entries]
        lines.append(f"| {row_label(algo)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def finetune_runs(results: ResultsFolder, training: list[dict[str, Any]], evaluations: list[dict[str, Any]]
                  ) -> list[dict[str, Any]]:  # fmt: skip
    """Per fine-tuning run: its start (the final evaluation of the model it started from on its task), the lowest
    evaluation in the first :data:`EARLY_SHARE` of its env steps, the early dip (that minus the start: negative is a
    dip), and its best evaluation."""
    final = {(r["algo"], r["seed"], r["task"]): r["success_rate"] for r in evaluations}
    rows = []
    for record in sorted(training, key=lambda r: (algo_rank(r["algo"]), r["seed"])):
        base, task = finetune_parts(record["algo"])
        if task is None or not record.get("log_folder"):
            continue
        steps, rates = Run.read(results.root / record["log_folder"], task, outside_start=True).evaluations()
        early = rates[steps <= EARLY_SHARE * record["training_steps"]]
        start = final.get((base, record["seed"], task))
        lowest = float(early.min()) if len(early) else None
        rows.append({
            "algo": record["algo"], "seed": record["seed"], "task": task, "start": start, "lowest_early": lowest,
            "early_dip": None if start is None or lowest is None else lowest - start,
            "best_eval_success_rate": record["best_eval_success_rate"], "best_step": record["best_step"],
            "training_steps": record["training_steps"],
        })  # fmt: skip
    return rows


def finetune_table(rows: list[dict[str, Any]]) -> str:
    """The fine-tuning runs' start, early dip and best evaluation, as a markdown table ('' without any)."""
    if not rows:
        return ""

    def number(value: float | None) -> str:
        return "n/a" if value is None else f"{value:.3f}"

    lines = [
        f"Fine-tuning runs: start (the starting model's final evaluation on the task), lowest evaluation in the first "
        f"{EARLY_SHARE:.0%} of the env steps and its difference from the start (negative: a dip), best evaluation "
        "during fine-tuning (its step).",
        "",
        "| row | seed | start | lowest early | early dip | best evaluation |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        best = f"{number(row['best_eval_success_rate'])} ({row['best_step']} of {row['training_steps']})"
        lines.append(f"| {row_label(row['algo'])} | {row['seed']} | {number(row['start'])} | "
                     f"{number(row['lowest_early'])} | {number(row['early_dip'])} | {best} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def make_report(results: ResultsFolder, tasks: list[str]) -> dict[str, Any]:
    """Write ``results.json``, ``results.csv`` and ``table.md`` from the records in ``results``; return the JSON."""
    protocol = read_json(results.protocol) or {}
    system = read_json(results.root / "system.json") or {}
    training, evaluations = results.training_records(), results.evaluation_records()
    matrices = success_matrix(evaluations, tasks)
    summary = summarise(matrices, tasks) if matrices else {}
    finetuning = finetune_runs(results, training, evaluations)
    report = {"settings": protocol.get("settings"), "train_env": protocol.get("train_env"), "tasks": tasks, "system": system,
              "summary": summary, "training": training, "evaluations": evaluations, "finetuning": finetuning}  # fmt: skip
    write_json(results.root / "results.json", report)
    versions = system.get("versions", {})
    machine = {**{key: system.get(key) for key in ("commit", "cpu_model", "cpu_count")},
               **{key: versions.get(key) for key in ("torch", "stable-baselines3")}}  # fmt: skip
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, extrasaction="ignore")
    writer.writeheader()
    for record in sorted(evaluations, key=lambda r: (algo_rank(r["algo"]), r["seed"], r["task"])):
        writer.writerow({**record, **machine})
    write_text(results.root / "results.csv", buffer.getvalue())
    episodes = (protocol.get("settings") or {}).get("episodes", 0)
    finetuned = finetune_table(finetuning)
    write_text(results.root / "table.md", markdown_table(summary, tasks, episodes) + (f"\n{finetuned}" if finetuned else ""))
    return report
