"""The thesis's figures from the protocol's results folder (matplotlib, Agg, PNG):

- ``training_success.png``: evaluation success rate during training, mean and 95% CI across seeds (figure 5.1);
- ``training_losses.png``: policy loss and CQL's Q predictions on the data during training (figure 5.2);
- ``final_success.png``: final success rate per task and algorithm, seeds as dots (figure 5.3);
- ``finetune_<task>.png``: evaluation success rate against env steps of the runs fine-tuned online on ``task``,
  mean and 95% CI across seeds, with the models they started from and the regrasping PD controller as lines;
- ``filmstrip_<task>.png``: frames of one episode of each policy (figure 5.6).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from scipy import stats  # noqa: E402

import envs  # noqa: E402
from sb3_cql.protocol.records import ResultsFolder, finetune_parts  # noqa: E402
from sb3_cql.protocol.report import algo_order, row_label  # noqa: E402
from sb3_cql.protocol.runs import Run  # noqa: E402

#: TensorBoard tags of figure 5.2: the policy loss (every algorithm) and the Q predictions on the data (CQL).
LOSS_TAGS = {"train/actor_loss": "policy loss", "train/cql_q_data": "Q(s, a) on the data"}
#: Frames of a filmstrip, evenly spaced from the first to the last step of the episode.
FILMSTRIP_FRAMES = 6
DPI = 120


def mean_ci95(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean over the rows of ``curves`` (seeds x points) and the half-width of its Student-t 95% CI (0 for 1 seed)."""
    mean = curves.mean(axis=0)
    if len(curves) < 2:
        return mean, np.zeros_like(mean)
    return mean, stats.t.ppf(0.975, len(curves) - 1) * curves.std(axis=0, ddof=1) / np.sqrt(len(curves))


def _on_common_steps(series: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """The steps every seed has, and the seeds' values there (seeds x steps)."""
    common = series[0][0]
    for steps, _ in series[1:]:
        common = np.intersect1d(common, steps)
    rows = [dict(zip(steps.tolist(), values.tolist(), strict=True)) for steps, values in series]
    return common, np.array([[row[step] for step in common.tolist()] for row in rows]).reshape(len(rows), len(common))


def _runs(results: ResultsFolder, training: list[dict[str, Any]], finetuned: bool = False) -> dict[str, list[Run]]:
    """The offline runs (or with ``finetuned`` the fine-tuning runs) of each row, read from their zoo folders."""
    runs: dict[str, list[Run]] = {}
    for record in training:
        if bool(record.get("started_from")) != finetuned:
            continue
        folder = results.run_dir(record["seed"]) / record["algo"]  # records made before log_folder was kept
        if record.get("log_folder"):
            folder = results.root / record["log_folder"]
        runs.setdefault(record["algo"], []).append(Run.read(folder, record["train_env"], outside_start=finetuned))
    return {algo: runs[algo] for algo in algo_order(runs)}


def _band(axis: plt.Axes, series: list[tuple[np.ndarray, np.ndarray]], label: str) -> bool:
    """The seeds' mean and 95% CI on the steps they all have; whether there was any series to plot."""
    if not series:
        return False
    steps, curves = _on_common_steps(series)
    mean, half = mean_ci95(curves)
    (line,) = axis.plot(steps, mean, label=f"{label} ({len(curves)} seeds)")
    axis.fill_between(steps, mean - half, mean + half, color=line.get_color(), alpha=0.25)
    return True


def _save(figure: plt.Figure, path: Path) -> None:
    figure.tight_layout()
    figure.savefig(path, dpi=DPI)
    plt.close(figure)


def training_success(results: ResultsFolder, runs: dict[str, list[Run]], pid_rate: float | None, path: Path) -> None:
    """Figure 5.1 from the runs' stitched evaluations."""
    figure, axis = plt.subplots(figsize=(7, 4))
    for algo, algo_runs in runs.items():
        _band(axis, [run.evaluations() for run in algo_runs if len(run.evaluations()[0])], algo.upper())
    if pid_rate is not None:
        axis.axhline(pid_rate, color="black", linestyle="--", label="PID (final evaluation)")
    axis.set(xlabel="training step", ylabel="evaluation success rate", ylim=(-0.05, 1.05), title="Panda-v0, during training")
    axis.legend()
    _save(figure, path)


def finetune_success(runs: dict[str, list[Run]], summary: dict[str, dict[str, Any]], task: str, path: Path) -> None:
    """Evaluations during the fine-tuning on ``task`` against env steps, beside the final evaluations on ``task`` of
    the models they started from and of the regrasping PD controller."""
    figure, axis = plt.subplots(figsize=(7, 4))
    for row, row_runs in runs.items():
        if _band(axis, [run.evaluations() for run in row_runs if len(run.evaluations()[0])], row_label(row)):
            base = finetune_parts(row)[0]
            start = summary.get(base, {}).get(task)
            if start is not None:
                axis.axhline(start["mean"], color="gray", linestyle=":", label=f"start: {base.upper()} (final evaluation)")
    teacher = summary.get("pid-regrasp", {}).get(task)
    if teacher is not None:
        axis.axhline(teacher["mean"], color="black", linestyle="--", label="PID-REGRASP (final evaluation)")
    axis.set(xlabel="env step of the fine-tuning", ylabel="evaluation success rate", ylim=(-0.05, 1.05),
             title=f"{task}, during online fine-tuning")  # fmt: skip
    axis.legend()
    _save(figure, path)


def training_losses(runs: dict[str, list[Run]], path: Path) -> None:
    """Figure 5.2 from the runs' TensorBoard logs."""
    figure, axes = plt.subplots(1, len(LOSS_TAGS), figsize=(6 * len(LOSS_TAGS), 4))
    for axis, (tag, label) in zip(axes, LOSS_TAGS.items(), strict=True):
        for algo, algo_runs in runs.items():
            _band(axis, [scalars for scalars in (run.scalars(tag) for run in algo_runs) if len(scalars[0])], algo.upper())
        axis.set(xlabel="training step", ylabel=label, title=tag)
        if axis.has_data():
            axis.legend()
    _save(figure, path)


def final_success(summary: dict[str, dict[str, Any]], evaluations: list[dict[str, Any]], tasks: list[str], path: Path) -> None:
    """Figure 5.3: bars of the mean over seeds with its 95% CI, one dot per seed."""
    figure, axis = plt.subplots(figsize=(8, 4))
    algos = list(summary)
    width = 0.8 / max(len(algos), 1)
    rng = np.random.default_rng(0)  # dot jitter only
    for index, algo in enumerate(algos):
        positions = np.arange(len(tasks)) + (index - (len(algos) - 1) / 2) * width
        means = [summary[algo][task]["mean"] for task in tasks]
        bars = axis.bar(positions, means, width=width * 0.9, label=row_label(algo), alpha=0.7)
        for position, task in zip(positions, tasks, strict=True):
            rates = [r["success_rate"] for r in evaluations if r["algo"] == algo and r["task"] == task]
            mean, half = mean_ci95(np.array(rates).reshape(-1, 1))
            axis.errorbar(position, mean, yerr=half, color="black", capsize=3)
            jitter = rng.uniform(-width / 4, width / 4, len(rates))
            axis.scatter(position + jitter, rates, color=bars.patches[0].get_facecolor(), edgecolor="black", zorder=3, s=16)
    axis.set_xticks(np.arange(len(tasks)), tasks)
    axis.set(ylabel="success rate", ylim=(-0.05, 1.05), title="Final evaluation of the best models")
    axis.legend()
    _save(figure, path)


def alignment_histograms(rows: dict[str, list[dict[str, Any]]], task: str, path: Path) -> None:
    """How the fingers closed on a lying cylinder, one panel a row (five a line): the share of its closings in each bin of
    ``sb3_cql.evaluate.ANGLE_BINS`` (the angle between the closing direction and the cylinder's axis; 90: across it),
    pooled over the row's records (``python -m sb3_cql.evaluate ... --output`` files, one a seed), with the row's mean
    success rate on ``task`` in its title."""
    from sb3_cql.evaluate import ANGLE_BINS  # the evaluation's bins, one home

    columns = min(len(rows), 5)
    lines = -(-len(rows) // columns)
    figure, axes = plt.subplots(lines, columns, figsize=(3.0 * columns, 3.0 * lines + 0.4), sharey=True, squeeze=False)
    for axis in axes.flat[len(rows) :]:
        axis.set_visible(False)
    for axis, (label, records) in zip(axes.flat, rows.items(), strict=False):
        episodes = [episode for record in records for episode in record["tasks"][task]["episodes"]]
        angles = [angle for episode in episodes for angle in episode["closing_angles"] if angle is not None]
        counts, _ = np.histogram(angles, bins=ANGLE_BINS)
        axis.bar(ANGLE_BINS[:-1], counts / max(len(angles), 1), width=np.diff(ANGLE_BINS), align="edge", edgecolor="black")
        rate = np.mean([record["tasks"][task]["success_rate"] for record in records])
        runs = f"{len(records)} run{'s' if len(records) > 1 else ''}"
        axis.set(title=f"{label}\nsuccess {rate:.2f} ({runs})", xlim=(0, 90))
        axis.set_xticks(ANGLE_BINS[::3])
        axis.set_xlabel(f"closing angle (deg), {len(angles)} closings")
    for axis in axes[:, 0]:
        axis.set_ylabel("share of closings")
    figure.suptitle(f"{task}: how the fingers closed on a lying cylinder (90: across its axis)")
    _save(figure, path)


def episode_frames(
    policy: Any, env_id: str, seed: int, env_kwargs: dict[str, Any], n_frames: int = FILMSTRIP_FRAMES
) -> tuple[list[np.ndarray], list[int]]:
    """``n_frames`` frames evenly spaced over one deterministic episode of ``policy`` (reset with ``seed``), and their
    steps. The episode is played twice, since it is bit-identical given the seed: once for its length, once to
    render only the chosen steps."""
    import gymnasium as gym

    def play(render_at: set[int] | None) -> tuple[int, list[np.ndarray]]:
        env = gym.make(env_id, render_mode="rgb_array", **env_kwargs)
        observation, _ = env.reset(seed=seed)
        if isinstance(policy, envs.PDController):  # its random yaws, the same in both plays
            policy.seed(seed)
        frames, step, done, state = [], 0, False, None
        while True:
            if render_at is not None and step in render_at:
                frames.append(env.render())
            if done:
                break
            action, state = policy.predict(observation, state, np.array([step == 0]), deterministic=True)
            observation, _, terminated, truncated, _ = env.step(action)
            done, step = terminated or truncated, step + 1
        env.close()
        return step, frames

    length, _ = play(None)
    steps = sorted({int(round(step)) for step in np.linspace(0, length, n_frames)})
    return play(set(steps))[1], steps


def filmstrip(policies: dict[str, tuple[Any, dict[str, Any]]], env_id: str, seed: int, path: Path) -> None:
    """Figure 5.6 for ``env_id``: one row of frames per policy (given with the env keywords it acts in)."""
    rows = {name: episode_frames(policy, env_id, seed, env_kwargs) for name, (policy, env_kwargs) in policies.items()}
    n_columns = max(len(frames) for frames, _ in rows.values())
    figure, axes = plt.subplots(len(rows), n_columns, figsize=(2.4 * n_columns, 1.9 * len(rows)), squeeze=False)
    for row, (name, (frames, steps)) in zip(axes, rows.items(), strict=True):
        for column, axis in enumerate(row):
            axis.axis("off")
            if column < len(frames):
                axis.imshow(frames[column])
                axis.set_title(f"step {steps[column]}", fontsize=8)
        row[0].text(-0.05, 0.5, name, transform=row[0].transAxes, ha="right", va="center", fontsize=10)
    figure.suptitle(f"{env_id}, episode seed {seed}")
    _save(figure, path)


def make_figures(results: ResultsFolder, report: dict[str, Any], filmstrips: bool = True) -> list[Path]:
    """Every figure of the module docstring from ``report`` (:func:`~sb3_cql.protocol.report.make_report`) and the
    runs on disk; filmstrips show the best model of each algorithm's smallest seed, in an episode reset with the
    smallest seed. Return the files written."""
    from sb3_cql.evaluate import load_policy

    results.figures.mkdir(parents=True, exist_ok=True)
    tasks, summary, training = report["tasks"], report["summary"], report["training"]
    written = []
    runs = _runs(results, training)
    if runs:
        pid = summary.get("pid", {}).get(report["train_env"])
        written.append(results.figures / "training_success.png")
        training_success(results, runs, None if pid is None else pid["mean"], written[-1])
        written.append(results.figures / "training_losses.png")
        training_losses(runs, written[-1])
    finetuned = _runs(results, training, finetuned=True)
    for task in sorted({finetune_parts(row)[1] for row in finetuned}):
        written.append(results.figures / f"finetune_{task}.png")
        on_task = {row: row_runs for row, row_runs in finetuned.items() if finetune_parts(row)[1] == task}
        finetune_success(on_task, summary, task, written[-1])
    if summary:
        written.append(results.figures / "final_success.png")
        final_success(summary, report["evaluations"], tasks, written[-1])
    if filmstrips:
        first_runs = {}
        for record in sorted(training, key=lambda r: r["seed"]):
            first_runs.setdefault(record["algo"], record)
        for algo, record in list(first_runs.items()):
            if not (results.root / record["best_model"]).is_file():  # models are not kept with the records
                print(f"filmstrips: {algo} left out, its model {results.root / record['best_model']} is not on disk",
                      flush=True)  # fmt: skip
                del first_runs[algo]
        for task in tasks:
            policies = {}
            for algo in algo_order([*first_runs, *summary]):
                if algo in envs.CONTROLLERS:
                    policies[algo.upper()] = load_policy(algo, None, task), {}
                elif algo in first_runs:
                    record = first_runs[algo]
                    model = load_policy(str(results.root / record["best_model"]), finetune_parts(algo)[0], task)
                    policies[row_label(algo)] = model, record.get("env_kwargs", {})
            seeds = [record["seed"] for record in [*training, *report["evaluations"]]]
            if policies and seeds:
                seed = min(seeds)
                written.append(results.figures / f"filmstrip_{task}.png")
                filmstrip(policies, task, seed, written[-1])
    return written
