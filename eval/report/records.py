"""Metric records: the flat schema of ``metrics.json`` / ``metrics.csv``, how evaluations become
records (:func:`metric_records`, :func:`robustness_records`), how records are indexed for tables
and plots (:func:`index_records`), and their JSON / CSV files (:func:`write_metrics`,
:func:`read_metrics`).

A record is a flat dict, one per (model, rate, class), with the keys of :data:`RECORD_FIELDS`:
strings for ``model`` and ``class``, ints for ``class_id``, ``n_gt`` and ``n_det``, floats
otherwise (nan where missing; ``null`` in JSON, empty in CSV).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rainbench.eval.metrics.robustness import mpc, percent_drop, rpc
from rainbench.store.classes import CLASS_NAMES

from rainbench.store.images import file_error
from .paper import TABLE_CLASS_ORDER

if TYPE_CHECKING:
    from rainbench.eval.metrics.bootstrap import BootstrapCI
    from rainbench.eval.metrics.evaluation import ClassMetrics

RECORD_FIELDS: tuple[str, ...] = (
    "model",
    "rate",
    "class",
    "class_id",
    "n_gt",
    "n_det",
    "ap50",
    "ap75",
    "ap50_95",
    "precision",
    "recall",
    "f1",
    "best_conf",
    "precision_at_conf",
    "recall_at_conf",
    "f1_at_conf",
    "conf",
    "ap50_ci_low",
    "ap50_ci_high",
    "ap50_95_ci_low",
    "ap50_95_ci_high",
    "ap50_drop_pct",
    "ap50_95_drop_pct",
    "f1_drop_pct",
    "f1_at_conf_drop_pct",
)
"""Keys of every :func:`metric_records` record, in column order."""

DROP_METRICS = ("ap50", "ap50_95", "f1", "f1_at_conf")
"""Metrics that get a ``<metric>_drop_pct`` column (percent drop from the clean rate)."""

_STRING_FIELDS = frozenset({"model", "class"})
"""Record keys read back as strings."""

_INT_FIELDS = frozenset({"class_id", "n_gt", "n_det"})
"""Record keys read back as ints."""


def as_float(value: Any) -> float:
    """float(value), with None (a JSON null) read as nan."""
    return float("nan") if value is None else float(value)


def is_missing(value: Any) -> bool:
    """True for None and float nan."""
    return value is None or (isinstance(value, float) and math.isnan(value))


def metric_records(
    results: Mapping[tuple[str, float], Mapping[int, ClassMetrics]],
    cis: Mapping[tuple[str, float], Mapping[int, BootstrapCI]]
    | Sequence[Mapping[tuple[str, float], Mapping[int, BootstrapCI]]]
    | None = None,
    *,
    clean_rate: float = 0.0,
    class_names: Sequence[str] = CLASS_NAMES,
) -> list[dict[str, Any]]:
    """Flatten evaluations into one record per (model, rate, class).

    Args:
        results: ``{(model, rate_mm_h): {class_id: ClassMetrics}}`` (e.g. outputs of
            :func:`rainbench.eval.metrics.evaluation.evaluate`).
        cis: Optional bootstrap intervals ``{(model, rate): {class_id: BootstrapCI}}``, or a
            sequence of such mappings (one per metric); fills ``<metric>_ci_low/high``.
        clean_rate: The reference rate of the ``*_drop_pct`` columns.
        class_names: ``class_names[class_id]`` is written as ``class``.

    Returns:
        Records with exactly the keys of ``RECORD_FIELDS``, ordered by model (first appearance),
        rate (ascending), then class (mapping order). Missing values are nan, e.g. the CI columns
        without ``cis`` and the drop columns when the model has no clean-rate result.
    """
    if cis is None:
        ci_maps: list[Mapping] = []
    elif isinstance(cis, Mapping):
        ci_maps = [cis]
    else:
        ci_maps = list(cis)
    models: list[str] = []
    for model, _rate in results:
        if model not in models:
            models.append(model)
    nan = float("nan")
    records = []
    for model in models:
        rates = sorted(float(rate) for m, rate in results if m == model)
        keys = {float(rate): (m, rate) for m, rate in results if m == model}
        clean_key = keys.get(float(clean_rate))
        clean = results[clean_key] if clean_key is not None else {}
        for rate in rates:
            key = keys[rate]
            for class_id, metrics in results[key].items():
                if not 0 <= class_id < len(class_names):
                    raise ValueError(
                        f"results[{key}]: class id {class_id} has no name in class_names {tuple(class_names)}"
                    )
                record = {field: nan for field in RECORD_FIELDS}
                values = dataclasses.asdict(metrics)
                record.update({name: values[name] for name in RECORD_FIELDS if name in values})
                record.update({"model": model, "rate": rate, "class": class_names[class_id], "class_id": class_id})
                for ci_map in ci_maps:
                    interval = ci_map.get(key, {}).get(class_id)
                    if interval is not None:
                        record[f"{interval.metric}_ci_low"] = interval.low
                        record[f"{interval.metric}_ci_high"] = interval.high
                reference = clean.get(class_id)
                for name in DROP_METRICS:
                    record[f"{name}_drop_pct"] = (
                        percent_drop(getattr(reference, name), values[name]) if reference is not None else nan
                    )
                records.append({field: record[field] for field in RECORD_FIELDS})
    return records


def robustness_records(
    records: Sequence[Mapping[str, Any]], metrics: Sequence[str] = ("ap50", "f1")
) -> list[dict[str, Any]]:
    """mPC / rPC per (model, class, metric) from :func:`metric_records` records.

    Args:
        records: Records with at least ``model``, ``rate`` (mm/h), ``class`` and the ``metrics``
            keys; values may be nan or None (JSON null).
        metrics: Record keys to summarise.

    Returns:
        Records ``{model, class, metric, clean, worst_rate, at_worst_rate, drop_pct, mpc, rpc}``
        in first-appearance order: ``clean`` is P, the value at rate 0 (nan without one),
        ``worst_rate`` the highest rate present, ``drop_pct`` the percent drop there, mPC the
        mean over rates > 0 (nan without any), rPC = mPC / P.
    """
    groups: dict[tuple[str, str], dict[float, Mapping[str, Any]]] = {}
    for record in records:
        groups.setdefault((record["model"], record["class"]), {})[float(record["rate"])] = record
    nan = float("nan")
    summary = []
    for (model, class_name), by_rate in groups.items():
        for metric in metrics:
            values = {rate: as_float(by_rate[rate][metric]) for rate in sorted(by_rate)}
            worst_rate = max(values)
            clean = values.get(0.0, nan)
            has_rain = worst_rate > 0
            summary.append(
                {
                    "model": model,
                    "class": class_name,
                    "metric": metric,
                    "clean": clean,
                    "worst_rate": worst_rate,
                    "at_worst_rate": values[worst_rate],
                    "drop_pct": percent_drop(clean, values[worst_rate]),
                    "mpc": mpc(values) if has_rain else nan,
                    "rpc": rpc(values) if has_rain and 0.0 in values else nan,
                }
            )
    return summary


def index_records(records: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[float], list[str], dict]:
    """Index records for tables and plots.

    Args:
        records: Records with at least ``model``, ``rate`` (mm/h) and ``class``.

    Returns:
        (models in first-appearance order, rates ascending as floats, classes in the paper's
        table order first (:data:`rainbench.eval.report.paper.TABLE_CLASS_ORDER`) then the others
        in class-id order, ``{(model, rate, class): record}``).
    """
    models: list[str] = []
    classes_seen: list[str] = []
    by_key = {}
    for record in records:
        model, class_name = record["model"], record["class"]
        if model not in models:
            models.append(model)
        if class_name not in classes_seen:
            classes_seen.append(class_name)
        by_key[(model, float(record["rate"]), class_name)] = record
    rates = sorted({float(record["rate"]) for record in records})
    others = [c for c in classes_seen if c not in TABLE_CLASS_ORDER]
    others.sort(key=lambda c: CLASS_NAMES.index(c) if c in CLASS_NAMES else len(CLASS_NAMES))
    classes = [c for c in TABLE_CLASS_ORDER if c in classes_seen] + others
    return models, rates, classes, by_key


def json_ready(value: Any) -> Any:
    """A JSON-serialisable copy of ``value``: nan/inf -> None, numpy scalars -> Python."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _field_order(records: Sequence[Mapping[str, Any]]) -> list[str]:
    """RECORD_FIELDS present in the records first, then any other keys by first appearance."""
    present: dict[str, None] = {}
    for record in records:
        for key in record:
            present.setdefault(key, None)
    ordered = [field for field in RECORD_FIELDS if field in present]
    return ordered + [key for key in present if key not in RECORD_FIELDS]


def write_metrics(records: Sequence[Mapping[str, Any]], out_dir: str | Path) -> tuple[Path, Path]:
    """Write records as ``metrics.json`` (a JSON list, nan -> null) and ``metrics.csv`` (nan -> empty).

    Args:
        records: Flat metric records (dicts of str / int / float / None).
        out_dir: Output folder, created if missing.

    Returns:
        (path of metrics.json, path of metrics.csv).

    Raises:
        OSError: one line naming the file that could not be written.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = _field_order(records)
    cleaned = [{key: json_ready(record.get(key)) for key in fields} for record in records]
    json_path = out_dir / "metrics.json"
    try:
        json_path.write_text(json.dumps(cleaned, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    except OSError as error:
        raise file_error(error, json_path) from error
    csv_path = out_dir / "metrics.csv"
    try:
        with csv_path.open("w", newline="", encoding="utf-8") as handle:
            writer = csv.DictWriter(handle, fieldnames=fields)
            writer.writeheader()
            for record in cleaned:
                writer.writerow({key: "" if value is None else value for key, value in record.items()})
    except OSError as error:
        raise file_error(error, csv_path) from error
    return json_path, csv_path


def _parse_csv_value(field: str, text: str) -> Any:
    """Type a CSV cell: strings for model/class, int counts, floats otherwise (empty -> nan)."""
    if field in _STRING_FIELDS:
        return text
    if text == "":
        return float("nan")
    if field in _INT_FIELDS:
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def read_metrics(path: str | Path) -> list[dict[str, Any]]:
    """Read ``metrics.json`` or ``metrics.csv`` back into records (null / empty -> nan).

    Args:
        path: A file written by :func:`write_metrics` (suffix .json or .csv).

    Returns:
        Records with the written keys; numbers as int (``class_id``, ``n_gt``, ``n_det``) or
        float, ``model`` and ``class`` as str.
    """
    path = Path(path)
    if path.suffix == ".json":
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, list):
            raise ValueError(f"{path}: expected a JSON list of records, got {type(data).__name__}")
        return [
            {
                key: float("nan") if value is None and key not in _STRING_FIELDS else value
                for key, value in record.items()
            }
            for record in data
        ]
    if path.suffix == ".csv":
        with path.open(newline="", encoding="utf-8") as handle:
            return [{key: _parse_csv_value(key, text) for key, text in row.items()} for row in csv.DictReader(handle)]
    raise ValueError(f"{path}: expected a .json or .csv metrics file, got suffix {path.suffix!r}")
