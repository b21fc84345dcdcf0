"""The thesis's evaluation protocol in one resumable command: train each algorithm on Panda-v0 with each seed
(RL-Zoo3, our hyperparams/), evaluate the best model of each run and the PD controller on the three tasks, and make
the table and figures.

    python -m sb3_cql.protocol                                   # 5 seeds, cql bc pid pid-regrasp sac, 100 episodes a task
    python -m sb3_cql.protocol --quick                           # 1 seed, 2,000 steps, 20 episodes: minutes
    python -m sb3_cql.protocol --algos cql pid --seeds 117 573 --workers 2
    python -m sb3_cql.protocol --ray auto --results-dir /shared/results          # on a Ray cluster
    python -m sb3_cql.protocol --report-only                     # table and figures again from results/
    python -m sb3_cql.protocol --dataset sb3cql/Panda-v0/noisy-regrasp-delta-v0   # the thesis's 10,000 episodes
    python -m sb3_cql.protocol --algos cql pid-regrasp --finetune PandaForce-v0     # + online fine-tuning rows

Every finished training and evaluation is recorded in the results folder, and the same command skips them; a
killed training continues from its latest checkpoint (``--save-freq``). ``--finetune TASK`` adds a stage: each
seed's best CQL model fine-tuned online on TASK (hyperparams/cql_finetune.yml), a row of its own that used
interaction with TASK, which it is then scored on too. Ctrl-C (or SIGTERM) ends it at once on one line, with status
130 (143): the units recorded stay, and the same command continues with the others.
"""

from __future__ import annotations

import argparse
import shlex
import sys

import envs
from sb3_cql.processes import exit_status, run_command
from sb3_cql.protocol.records import ResultsFolder, read_json
from sb3_cql.protocol.runner import DEFAULT_ALGOS, THESIS_SEEDS, Protocol, ProtocolError, Settings, UnitsFailed
from sb3_cql.protocol.schedule import run_protocol

#: ``--quick``: training steps, evaluation every ... steps over ... episodes, checkpoints, final episodes.
QUICK = {"n_timesteps": 2000, "eval_freq": 1000, "eval_episodes": 5, "save_freq": 1000, "episodes": 20}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m sb3_cql.protocol", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    parser.add_argument("--algos", nargs="+", default=list(DEFAULT_ALGOS),
                        help=f"RL-Zoo3 algorithms, and the PD controllers: {', '.join(envs.CONTROLLERS)}")  # fmt: skip
    parser.add_argument("--seeds", nargs="+", type=int, default=None, help=f"default: {' '.join(map(str, THESIS_SEEDS))}")
    parser.add_argument("--tasks", nargs="+", default=list(envs.ENV_IDS), choices=list(envs.ENV_IDS))
    parser.add_argument("--results-dir", default="results")
    parser.add_argument("--workers", type=int, default=1, help="worker processes (zoo runs get 1 torch thread if > 1)")
    parser.add_argument("--ray", metavar="ADDRESS", default=None,
                        help="run the units as Ray tasks on the cluster at ADDRESS (auto, host:port or ray://host:port), "
                             "as many at a time as it has CPUs (or --workers); the results folder must be on storage "
                             "every node sees")  # fmt: skip
    parser.add_argument("--quick", action="store_true", help="1 seed, short training, 20 final episodes")
    parser.add_argument("--n-timesteps", type=int, default=None, help="training steps of every run (default: configs)")
    parser.add_argument("--eval-freq", type=int, default=None, help="steps between evaluations in training (default: configs)")
    parser.add_argument("--eval-episodes", type=int, default=None, help="episodes of those evaluations (default: configs)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes of each final evaluation (default 100)")
    parser.add_argument("--save-freq", type=int, default=None, help="steps between checkpoints (default 10,000)")
    parser.add_argument("--dataset", default=None, help="dataset of the offline algorithms (default: configs')")
    parser.add_argument("--zoo-args", default="", help='more rl_zoo3.train arguments, e.g. "--hyperparams batch_size:64"')
    parser.add_argument("--finetune", nargs="+", default=[], choices=list(envs.ENV_IDS), metavar="TASK",
                        help="fine-tune each seed's best CQL model online on these tasks: rows of their own")  # fmt: skip
    parser.add_argument("--finetune-args", default="", help="more rl_zoo3.train arguments of the fine-tuning runs, "
                        'e.g. "--hyperparams cql_alpha:0.0" (SAC fine-tuning)')  # fmt: skip
    parser.add_argument("--report-only", action="store_true", help="only make the table and figures from results/")
    parser.add_argument("--no-filmstrips", action="store_true", help="skip the filmstrip figures (they play episodes)")
    args = parser.parse_args(argv)

    results = ResultsFolder(args.results_dir)
    failed: UnitsFailed | None = None
    try:
        if not args.report_only:
            quick = QUICK if args.quick else {}
            seeds = args.seeds or (list(THESIS_SEEDS[:1]) if args.quick else list(THESIS_SEEDS))
            given = {name: getattr(args, name) for name in ("n_timesteps", "eval_freq", "eval_episodes", "episodes")}
            numbers = {name: value if value is not None else quick.get(name) for name, value in given.items()}
            if numbers["episodes"] is None:
                numbers["episodes"] = 100
            settings = Settings(**numbers, zoo_args=_split("--zoo-args", args.zoo_args), dataset=args.dataset,
                                finetune_args=_split("--finetune-args", args.finetune_args))  # fmt: skip
            save_freq = args.save_freq if args.save_freq is not None else quick.get("save_freq", 10_000)
            protocol = Protocol(
                results, args.algos, seeds, args.tasks, settings, save_freq, args.workers, args.finetune, args.ray
            )
            try:
                counts = run_protocol(protocol)
                print(f"units: {counts['done']} done, {counts['skipped']} already recorded", flush=True)
            except UnitsFailed as error:
                failed = error  # the report still shows everything else
        elif read_json(results.protocol) is None:
            raise ProtocolError(f"{results.root} holds no protocol results")
        make_outputs(results, args.tasks, filmstrips=not args.no_filmstrips)
    except ProtocolError as error:  # bad input, found before any work: a usage error
        print(f"python -m sb3_cql.protocol: error: {error}", file=sys.stderr)
        raise SystemExit(2) from None
    except KeyboardInterrupt as interrupt:
        print(f"interrupted: the units done are recorded in {results.root}; the same command continues with the others",
              file=sys.stderr)  # fmt: skip
        raise SystemExit(exit_status(interrupt)) from None
    if failed is not None:
        sys.exit(f"error: {failed}")


def _split(option: str, value: str) -> list[str]:
    """The words of ``value`` as the shell splits them; a :class:`ProtocolError` where it cannot (a quote left open)."""
    try:
        return shlex.split(value)
    except ValueError as error:
        raise ProtocolError(f"{option} {value!r}: {error} (close each quote)") from None


def make_outputs(results: ResultsFolder, tasks: list[str], filmstrips: bool = True) -> None:
    """Results files, table and figures from the records in ``results``, and where they are."""
    from sb3_cql.protocol.plots import make_figures
    from sb3_cql.protocol.report import make_report

    report = make_report(results, tasks)
    figures = make_figures(results, report, filmstrips=filmstrips)
    print(f"report: {results.root / 'table.md'}, {results.root / 'results.json'}, {results.root / 'results.csv'}, "
          f"{len(figures)} figures in {results.figures}", flush=True)  # fmt: skip
    print((results.root / "table.md").read_text(), flush=True)


if __name__ == "__main__":
    run_command(main)
