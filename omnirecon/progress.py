"""One progress-bar style for every long job: label, bar, done/total, elapsed time and ETA (rich)."""

from __future__ import annotations


def progress_bar(label: str = "{task.description}", unit: str = "", *extra, **kwargs):
    """A ``rich.progress.Progress`` showing ``label``, a bar, ``done/total [unit]``, elapsed time and the ETA,
    then ``extra`` columns; ``kwargs`` go to ``Progress`` (``disable``, ``transient``, ``console``)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = [TextColumn(label), BarColumn(), MofNCompleteColumn(), *([TextColumn(unit)] if unit else []),
               TimeElapsedColumn(), TextColumn("eta"), TimeRemainingColumn(), *extra]
    return Progress(*columns, **kwargs)
