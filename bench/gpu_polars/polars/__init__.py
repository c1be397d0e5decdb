"""A stand-in for polars on a lent GPU machine (bench/gpu_train.sh), which has no package
registry and where the 54 MB polars wheel does not fit the device tool's 64 MiB tree.

ultralytics' trainer uses polars for one thing while rainbench trains (plots off): reading its
``results.csv`` back into the checkpoint, ``polars.read_csv(data, infer_schema_length=None)
.to_dict(as_series=False)``. This module does that with the csv module: numbers as float (int
where the text is an integer), other cells as text. Anything else raises, naming this file.
"""

from __future__ import annotations

import csv
import io


class DataFrame:
    def __init__(self, columns: dict[str, list]) -> None:
        self._columns = columns

    def to_dict(self, as_series: bool = True) -> dict[str, list]:
        return {name: list(values) for name, values in self._columns.items()}


def _cell(text: str):
    text = text.strip()
    try:
        return int(text)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def read_csv(source, infer_schema_length=None, **_ignored) -> DataFrame:
    if isinstance(source, (bytes, bytearray)):
        text = bytes(source).decode()
    else:
        with open(source, encoding="utf-8") as handle:
            text = handle.read()
    rows = [row for row in csv.reader(io.StringIO(text)) if row]
    header = [name.strip() for name in rows[0]] if rows else []
    return DataFrame({name: [_cell(row[i]) for row in rows[1:]] for i, name in enumerate(header)})


def __getattr__(name: str):
    raise AttributeError(f"polars.{name}: not in rainbench's stand-in ({__file__}); only "
                         "read_csv(...).to_dict() is")
