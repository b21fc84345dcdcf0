"""The thesis's evaluation protocol (chapters 4.3 and 5): ``python -m sb3_cql.benchmark``.

:mod:`~sb3_cql.benchmark.runner` trains and evaluates (resumable units of work), :mod:`~sb3_cql.benchmark.runs`
reads a zoo training run back from disk, :mod:`~sb3_cql.benchmark.report` makes the results files and the table,
:mod:`~sb3_cql.benchmark.plots` the figures, :mod:`~sb3_cql.benchmark.records` holds the results folder's layout.
"""

from sb3_cql.benchmark.records import ResultsFolder
from sb3_cql.benchmark.runner import BenchmarkError, Protocol, Settings, UnitsFailed, run_protocol

__all__ = ["BenchmarkError", "Protocol", "ResultsFolder", "Settings", "UnitsFailed", "run_protocol"]
