"""The thesis's evaluation protocol (chapters 4.3 and 5): ``python -m sb3_cql.protocol``.

:mod:`~sb3_cql.protocol.runner` trains and evaluates (resumable units of work), :mod:`~sb3_cql.protocol.schedule`
runs the units not yet recorded, :mod:`~sb3_cql.protocol.runs`
reads a zoo training run back from disk, :mod:`~sb3_cql.protocol.report` makes the results files and the table,
:mod:`~sb3_cql.protocol.plots` the figures, :mod:`~sb3_cql.protocol.records` holds the results folder's layout.
"""

from sb3_cql.protocol.records import ResultsFolder
from sb3_cql.protocol.runner import Protocol, ProtocolError, Settings, UnitsFailed
from sb3_cql.protocol.schedule import run_protocol

__all__ = ["ProtocolError", "Protocol", "ResultsFolder", "Settings", "UnitsFailed", "run_protocol"]
