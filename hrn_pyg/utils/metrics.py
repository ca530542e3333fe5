"""Metric logs: an append-only CSV that survives a kill (its picture: :func:`hrn_pyg.viz.plot_curves`)."""

from __future__ import annotations

import csv
import os
from pathlib import Path

from hrn_pyg.utils.files import atomic_path


class CSVLog:
    """Append rows of named numbers to a CSV file (header once, rows flushed as they come); on resume
    ``truncate_after`` drops the rows past the checkpoint, so the log stays one history."""

    def __init__(self, path: str | os.PathLike, fields: list[str]):
        self.path = Path(path)
        self.fields = list(fields)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if not self.path.exists() or self.path.stat().st_size == 0:
            with open(self.path, "w", newline="") as fh:
                csv.writer(fh).writerow(self.fields)

    def append(self, row: dict[str, float | int | str]) -> None:
        with open(self.path, "a", newline="") as fh:
            csv.writer(fh).writerow([row.get(k, "") for k in self.fields])

    def read(self) -> list[dict[str, str]]:
        with open(self.path, newline="") as fh:
            return list(csv.DictReader(fh))

    def truncate_after(self, step: int) -> None:
        rows = [r for r in self.read() if r.get("step", "") != "" and int(float(r["step"])) <= step]
        with atomic_path(self.path) as tmp:
            with open(tmp, "w", newline="") as fh:
                w = csv.DictWriter(fh, fieldnames=self.fields)
                w.writeheader()
                w.writerows(rows)
