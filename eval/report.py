"""Writing, rendering and plotting of rainbench metric records (the paper's Tables III/IV, Figs. 8-12).

Records are the flat dicts of :func:`rainbench.eval.metrics.metric_records` (one per model, rate,
class). Rendering (:func:`render_report_md`) is a pure function returning text; the ``write_*``
and ``plot_*`` functions only write files. Plots use matplotlib's Agg canvas (no pyplot state, no
display, bundled DejaVu fonts only) and OpenCV's built-in Hershey fonts, so nothing is fetched.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.store.classes import CLASS_COLOURS, CLASS_NAMES

from .metrics import RECORD_FIELDS, percent_drop, robustness_records

PAPER_TABLES: dict[str, dict[str, dict[float, dict[str, float]]]] = {
    # Table III, "AP score" (YOLO val's per-class AP, read here as AP@0.5).
    "ap50": {
        "YOLOv4": {
            0.0: {"car": 0.64, "person": 0.771, "bicycle": 0.913, "motorcycle": 0.263},
            100.0: {"car": 0.424, "person": 0.469, "bicycle": 0.677, "motorcycle": 0.0043},
        },
        "YOLOv5x": {
            0.0: {"car": 0.652, "person": 0.738, "bicycle": 0.813, "motorcycle": 0.425},
            100.0: {"car": 0.452, "person": 0.427, "bicycle": 0.614, "motorcycle": 0.0031},
        },
        "YOLOv7x": {
            0.0: {"car": 0.669, "person": 0.731, "bicycle": 0.936, "motorcycle": 0.198},
            100.0: {"car": 0.46, "person": 0.51, "bicycle": 0.693, "motorcycle": 0.00025},
        },
    },
    # Table IV, "F1 score".
    "f1": {
        "YOLOv4": {
            0.0: {"car": 0.629, "person": 0.699, "bicycle": 0.802, "motorcycle": 0.179},
            100.0: {"car": 0.477, "person": 0.414, "bicycle": 0.627, "motorcycle": 0.0},
        },
        "YOLOv5x": {
            0.0: {"car": 0.623, "person": 0.746, "bicycle": 0.724, "motorcycle": 0.415},
            100.0: {"car": 0.514, "person": 0.485, "bicycle": 0.535, "motorcycle": 0.0},
        },
        "YOLOv7x": {
            0.0: {"car": 0.663, "person": 0.786, "bicycle": 0.859, "motorcycle": 0.159},
            100.0: {"car": 0.533, "person": 0.549, "bicycle": 0.522, "motorcycle": 0.0},
        },
    },
}
"""Published numbers of the seed paper, ``{metric: {model: {rate_mm_h: {class: value}}}}``.

Transcribed from Tables III (AP) and IV (F1), CARLA data, Normal (0 mm/h) and 100 mm/h. The
paper reports YOLO's "AP score" without naming the IoU; it is mapped to our ``ap50``. (Table II
repeats the Normal values, with one discrepancy: YOLOv4 car F1 is 0.628 there, 0.629 here.)
"""

TABLE_CLASS_ORDER: tuple[str, ...] = ("car", "person", "bicycle", "motorcycle")
"""Column order of the paper's Tables III and IV (other classes, e.g. bus and truck, follow in
class-id order)."""

PAPER_COLORS: dict[str, str] = {"yolov7x": "tab:red", "yolov5x": "tab:green", "yolov4": "tab:blue"}
"""Line colours of the paper's Figs. 8-11 (YOLOv7x red, YOLOv5x green, YOLOv4 blue)."""

METRIC_LABELS: dict[str, str] = {
    "ap50": "AP@0.5",
    "ap75": "AP@0.75",
    "ap50_95": "AP@0.5:0.95",
    "f1": "F1",
    "f1_at_conf": "F1 @ conf",
}
"""Axis labels of record metrics."""

_STRING_FIELDS = frozenset({"model", "class"})
_INT_FIELDS = frozenset({"class_id", "n_gt", "n_det"})


# --------------------------------------------------------------------------------------------
# metrics.json / metrics.csv
# --------------------------------------------------------------------------------------------


def _is_missing(value: Any) -> bool:
    """True for None and float nan."""
    return value is None or (isinstance(value, float) and math.isnan(value))


def _json_ready(value: Any) -> Any:
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
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    fields = _field_order(records)
    cleaned = [{key: _json_ready(record.get(key)) for key in fields} for record in records]
    json_path = out_dir / "metrics.json"
    json_path.write_text(json.dumps(cleaned, indent=1, allow_nan=False) + "\n", encoding="utf-8")
    csv_path = out_dir / "metrics.csv"
    with csv_path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        for record in cleaned:
            writer.writerow({key: "" if value is None else value for key, value in record.items()})
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


# --------------------------------------------------------------------------------------------
# report.md
# --------------------------------------------------------------------------------------------


def _value(value: Any) -> float:
    """float(value) with None -> nan."""
    return float("nan") if value is None else float(value)


def _fmt(value: Any) -> str:
    """Metric cell: 3 decimals, 2 significant digits below 0.01 (the paper's 0.0043), n/a for nan."""
    number = _value(value)
    if math.isnan(number):
        return "n/a"
    if number != 0 and abs(number) < 0.01:
        return f"{number:.2g}"
    return f"{number:.3f}"


def _fmt_pct(value: Any) -> str:
    """Percent cell with 2 decimals, n/a for nan."""
    number = _value(value)
    return "n/a" if math.isnan(number) else f"{number:.2f}"


def _rate_label(rate: float, clean_rate: float) -> str:
    """'Normal' for the clean rate, else e.g. '100mm/h' (the paper's labels)."""
    return "Normal" if rate == clean_rate else f"{rate:g}mm/h"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Markdown table lines."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def _index(records: Sequence[Mapping[str, Any]]) -> tuple[list[str], list[float], list[str], dict]:
    """Models (first appearance), rates (ascending), classes (paper order first, then the others
    in class-id order), {(m, r, c): record}."""
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


def _paper_model(model: str, paper_metric: Mapping[str, Any], paper_models: Mapping[str, str] | None) -> str | None:
    """The paper's name of ``model``: from ``paper_models``, else a case-insensitive exact match."""
    if paper_models is not None and model in paper_models:
        return paper_models[model] if paper_models[model] in paper_metric else None
    for name in paper_metric:
        if name.lower() == model.lower():
            return name
    return None


def _degradation_table(
    metric: str,
    models: Sequence[str],
    classes: Sequence[str],
    by_key: Mapping,
    clean_rate: float,
    heavy_rate: float,
    paper: Mapping[str, Any] | None,
    paper_models: Mapping[str, str] | None,
) -> list[str]:
    """Table III / IV layout: rows model x {Normal, heavy rate, % drop}, columns classes (with a
    paper column beside each class the paper reports)."""
    paper_metric = (paper or {}).get(metric)
    paper_classes = {name for by_rate in (paper_metric or {}).values() for values in by_rate.values()
                     for name in values}
    header = ["Model", "Condition"]
    for class_name in classes:
        header.append(class_name.capitalize())
        if class_name in paper_classes:
            header.append(f"{class_name.capitalize()} (paper)")
    rows = []
    for model in models:
        paper_name = _paper_model(model, paper_metric, paper_models) if paper_metric is not None else None
        paper_rates = paper_metric.get(paper_name, {}) if paper_name is not None else {}
        for position, rate in enumerate((clean_rate, heavy_rate, None)):
            row = [model if position == 0 else "", _rate_label(rate, clean_rate) if rate is not None else "% drop"]
            for class_name in classes:
                clean = _value(by_key.get((model, clean_rate, class_name), {}).get(metric))
                if rate is None:
                    row.append(
                        _fmt_pct(
                            percent_drop(clean, _value(by_key.get((model, heavy_rate, class_name), {}).get(metric)))
                        )
                    )
                else:
                    row.append(_fmt(by_key.get((model, rate, class_name), {}).get(metric)))
                if class_name in paper_classes:
                    published_clean = paper_rates.get(clean_rate, {}).get(class_name)
                    if rate is None:
                        published_heavy = paper_rates.get(heavy_rate, {}).get(class_name)
                        row.append(_fmt_pct(percent_drop(_value(published_clean), _value(published_heavy))))
                    else:
                        row.append(_fmt(paper_rates.get(rate, {}).get(class_name)))
            rows.append(row)
    return _table(header, rows)


def _rate_table(metric: str, models, rates, classes, by_key, clean_rate: float, cell) -> list[str]:
    """Rows model x class, one column per rate; ``cell(record)`` formats one value."""
    header = ["Model", "Class"] + [_rate_label(rate, clean_rate) for rate in rates]
    rows = []
    for model in models:
        for position, class_name in enumerate(classes):
            row = [model if position == 0 else "", class_name]
            row += [cell(by_key.get((model, rate, class_name), {})) for rate in rates]
            rows.append(row)
    return _table(header, rows)


def render_report_md(
    records: Sequence[Mapping[str, Any]],
    *,
    paper: Mapping[str, Any] | None = None,
    paper_models: Mapping[str, str] | None = None,
    clean_rate: float = 0.0,
    heavy_rate: float | None = None,
    title: str = "rainbench: detection under synthetic rain",
) -> str:
    """Render records as a markdown report in the paper's layout.

    Sections: Table III (AP@0.5) and Table IV (F1 at the YOLO best-F1 confidence) with rows
    model x {Normal, heavy rate, % drop} and columns the records' classes (car / person / bicycle
    / motorcycle in the paper's order, then e.g. bus / truck; a paper column beside the paper's); the
    full rate-by-rate tables of AP@0.5, AP@0.5:0.95 and F1; the 95 % bootstrap intervals of
    AP@0.5 (when the records carry them); mPC / rPC (Michaelis et al. 2019); ground-truth counts.

    Args:
        records: Records of :func:`rainbench.eval.metrics.metric_records` (or read back by
            :func:`read_metrics`).
        paper: Published numbers to put beside ours, e.g. :data:`PAPER_TABLES`
            (``{metric: {model: {rate: {class: value}}}}``); None leaves them out.
        paper_models: ``{our model name: paper model name}``; without it a model is matched to
            the paper's by case-insensitive name.
        clean_rate: Rate shown as "Normal".
        heavy_rate: Rate compared with Normal in Tables III/IV; the highest rate when None.
        title: Report title.

    Returns:
        The markdown text.
    """
    if not records:
        raise ValueError("records: expected at least one metric record, got none")
    models, rates, classes, by_key = _index(records)
    heavy = max(rates) if heavy_rate is None else float(heavy_rate)
    if heavy not in rates or float(clean_rate) not in rates:
        raise ValueError(
            f"clean_rate/heavy_rate: expected rates present in the records {rates}, got {clean_rate} and {heavy}"
        )
    clean_rate = float(clean_rate)
    lines = [f"# {title}", ""]
    lines += [
        f"Models: {', '.join(models)}. Rates: {', '.join(f'{r:g}' for r in rates)} mm/h. "
        "AP is COCO's 101-point interpolated AP (pycocotools, maxDets 100); F1, precision and recall "
        "are taken at the confidence maximising the mean F1 over classes (YOLO convention). "
        "% drop = 100 (Normal - rain) / Normal.",
        "",
    ]
    heavy_label = _rate_label(heavy, clean_rate)
    lines += [f"## Table III. AP@0.5 degradation, Normal vs {heavy_label}", ""]
    lines += _degradation_table("ap50", models, classes, by_key, clean_rate, heavy, paper, paper_models)
    lines += ["", f"## Table IV. F1 degradation, Normal vs {heavy_label}", ""]
    lines += _degradation_table("f1", models, classes, by_key, clean_rate, heavy, paper, paper_models)
    if paper is not None and set(classes) & set(TABLE_CLASS_ORDER):
        lines += ["", "Paper columns: the seed paper's published values (Tables III and IV), for reference."]
    for metric, label in (("ap50", "AP@0.5"), ("ap50_95", "AP@0.5:0.95"), ("f1", "F1")):
        lines += ["", f"## {label} by rainfall rate", ""]
        lines += _rate_table(metric, models, rates, classes, by_key, clean_rate, lambda r, m=metric: _fmt(r.get(m)))
    has_ci = any(not _is_missing(record.get("ap50_ci_low")) for record in records)
    if has_ci:
        lines += ["", "## AP@0.5 95 % bootstrap confidence intervals (frames resampled)", ""]
        lines += _rate_table(
            "ap50",
            models,
            rates,
            classes,
            by_key,
            clean_rate,
            lambda r: (
                "n/a"
                if _is_missing(r.get("ap50_ci_low"))
                else f"[{_fmt(r.get('ap50_ci_low'))}, {_fmt(r.get('ap50_ci_high'))}]"
            ),
        )
    lines += ["", "## Robustness: mPC (mean over rates > 0) and rPC = mPC / Normal", ""]
    summary = {(s["model"], s["class"], s["metric"]): s for s in robustness_records(records, ("ap50", "f1"))}
    header = ["Model", "Class", "AP@0.5 Normal", "AP@0.5 mPC", "AP@0.5 rPC", "F1 Normal", "F1 mPC", "F1 rPC"]
    rows = []
    for model in models:
        for position, class_name in enumerate(classes):
            row = [model if position == 0 else "", class_name]
            for metric in ("ap50", "f1"):
                entry = summary.get((model, class_name, metric))
                row += [_fmt(entry["clean"]), _fmt(entry["mpc"]), _fmt(entry["rpc"])] if entry else ["n/a"] * 3
            rows.append(row)
    lines += _table(header, rows)
    lines += ["", f"## Ground-truth instances (non-ignored), model {models[0]}", ""]
    lines += _table(
        ["Class"] + [_rate_label(rate, clean_rate) for rate in rates],
        [
            [class_name]
            + [
                "n/a"
                if _is_missing(by_key.get((models[0], rate, class_name), {}).get("n_gt"))
                else str(int(by_key[(models[0], rate, class_name)]["n_gt"]))
                for rate in rates
            ]
            for class_name in classes
        ],
    )
    return "\n".join(lines) + "\n"


PAPER_TABLE_I: dict[str, tuple[int, int]] = {
    "car": (6, 838), "person": (8, 350), "bicycle": (2, 67), "motorcycle": (1, 10),
}
"""The seed paper's Table I: (objects placed, labelled instances over the 200 frames) per class."""


def _fmt_rate(value: float) -> str:
    if math.isinf(value):
        return "> max rate"
    return "n/a" if math.isnan(value) else f"{value:.0f}"


def _weather_share(records_by_rain: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[str]:
    """Section comparing physical rain with and without the weather following the rate."""
    fixed = [name for name in records_by_rain if name.endswith("-fixed-weather")]
    if not fixed or fixed[0].removesuffix("-fixed-weather") not in records_by_rain:
        return []
    follows = fixed[0].removesuffix("-fixed-weather")
    models, rates, classes, with_weather = _index(records_by_rain[follows])
    _, _, _, without = _index(records_by_rain[fixed[0]])
    clean, heavy = min(rates), max(rates)
    rows = []
    for model in models:
        for position, class_name in enumerate(classes):
            def ap(table, rate):
                return table.get((model, rate, class_name), {}).get("ap50")

            drops = []
            for table in (with_weather, without):
                base, rainy = ap(table, clean), ap(table, heavy)
                drops.append(base - rainy if base is not None and rainy is not None else None)
            share = (f"{100 * (drops[0] - drops[1]) / drops[0]:.0f} %"
                     if None not in drops and drops[0] > 1e-9 else "n/a")
            rows.append([model if position == 0 else "", class_name,
                         _fmt(ap(with_weather, clean)), _fmt(ap(with_weather, heavy)),
                         _fmt(ap(without, heavy)), share])
    lines = [f"### How much of the AP loss is the weather? {follows} with the weather following "
             f"the rate vs {fixed[0]}", "",
             "Both datasets hold the same scene, actors and drops; only the world under the rain "
             "differs (sky, light, wet road, puddles, spray, exposure and noise follow the rate in "
             f"the first, and stay the base weather's in the second). Share = (AP loss with the "
             f"weather - AP loss without) / AP loss with the weather, at {_rate_label(heavy, clean)}.", ""]
    lines += _table(["Model", "Class", "AP@0.5 Normal", f"{heavy:g} mm/h, weather follows",
                     f"{heavy:g} mm/h, fixed weather", "Share of the loss from the weather"], rows)
    return lines + [""]


def render_paper_md(
    *,
    setup_lines: Sequence[str],
    table_one: Mapping[str, tuple[int, int]],
    records_by_rain: Mapping[str, Sequence[Mapping[str, Any]]],
    half_rates: Mapping[tuple[str, str, str], float],
    breakdowns: Mapping[str, Mapping[float, Mapping[str, Mapping[str, Any]]]],
    breakdown_model: str,
    paper_rain_model: str = "jeon2022",
) -> str:
    """The ``make paper`` report: our Tables I, III and IV beside the seed paper's, plots of both
    rain models, and the analyses beyond the paper. Every table shows the classes of the records
    (the evaluated ones: by default the paper's four; bus and truck when asked for), in the
    paper's order, then the others in class-id order; the paper's columns read n/a for classes it
    did not have.

    Args:
        setup_lines: Markdown lines describing the run (data, models, hardware, times).
        table_one: ``{class: (objects, instances)}`` of our dataset (a missing class counts 0).
        records_by_rain: ``{rain model: metric records}`` (:func:`metric_records`), each with the
            plots ``<rain model>/ap50_vs_rate.png`` and ``f1_vs_rate.png`` beside the report.
        half_rates: ``{(rain model, model, class): rate}`` where AP@0.5 falls to half its clean
            value (inf: never within the measured rates).
        breakdowns: ``{"visible fraction" | "box size": {rate: {bin: {class: BreakdownAP}}}}`` of
            ``breakdown_model`` under ``paper_rain_model`` rain.
        breakdown_model: The model of ``breakdowns``.
        paper_rain_model: The rain model of the paper's Tables III and IV comparison.
    """
    lines = ["# rainbench: the seed paper's experiment on rainbench data", ""]
    lines += list(setup_lines) + [""]
    classes = _index(next(iter(records_by_rain.values())))[2] if records_by_rain else list(TABLE_CLASS_ORDER)
    lines += ["## Table I. Objects and instances per class", ""]
    rows = []
    for class_name in classes:
        ours = table_one.get(class_name, (0, 0))
        paper = [str(v) for v in PAPER_TABLE_I[class_name]] if class_name in PAPER_TABLE_I else ["n/a", "n/a"]
        rows.append([class_name, str(ours[0]), str(ours[1]), *paper])
    lines += _table(["Class", "Objects", "Instances", "Objects (paper)", "Instances (paper)"], rows)
    for rain_model, records in records_by_rain.items():
        models, rates, rain_classes, by_key = _index(records)
        heavy, clean = max(rates), min(rates)
        label = ("the paper's calibrated drop law" if rain_model == paper_rain_model
                 else "physically based rain over the unchanged base weather"
                 if rain_model.endswith("-fixed-weather")
                 else "physically based rain, weather following the rate")
        rows_models = list(models)
        by_key = dict(by_key)
        if rain_model == paper_rain_model:  # the paper's published rows under ours
            for metric, by_model in PAPER_TABLES.items():
                for paper_model, by_rate in by_model.items():
                    name = f"{paper_model} (paper)"
                    if name not in rows_models:
                        rows_models.append(name)
                    for rate, by_class in by_rate.items():
                        for class_name, value in by_class.items():
                            by_key.setdefault((name, float(rate), class_name), {})[metric] = value
        for metric, table, metric_label in (("ap50", "III", "AP@0.5"), ("f1", "IV", "F1")):
            lines += ["", f"## Table {table}. {metric_label}, Normal vs {_rate_label(heavy, clean)}: "
                      f"{rain_model} ({label})", ""]
            lines += _degradation_table(metric, rows_models, rain_classes, by_key, clean, heavy, None, None)
        if rain_model == paper_rain_model:
            lines += ["", "Rows marked (paper): the seed paper's published Tables III and IV (COCO-pretrained "
                      "YOLOv4, YOLOv5x, YOLOv7x on its CARLA Town04 clip), for reference."]
        if any(model.endswith("-weak") for model in models):
            lines += ["", "Rows of a `-weak` model: a deliberately weak in-domain control (the nano "
                      "recipe's first epochs), whose clean AP is near the paper's detectors', so its "
                      "drop shows whether the paper's size of drop appears for a detector of the "
                      "paper's strength (docs/models.md)."]
        lines += ["", f"AP@0.5 and F1 against rain rate ({rain_model}):", "",
                  f"![AP@0.5 vs rate, {rain_model}]({rain_model}/ap50_vs_rate.png) "
                  f"![F1 vs rate, {rain_model}]({rain_model}/f1_vs_rate.png)", "",
                  f"Full rate-by-rate tables with bootstrap intervals: [{rain_model}/report.md]({rain_model}/report.md)."]
    lines += ["", "## Beyond the paper", ""]
    lines += _weather_share(records_by_rain)
    lines += ["### Rain rate (mm/h) at which AP@0.5 falls to half its clean value", ""]
    rain_models = list(records_by_rain)
    models = _index(next(iter(records_by_rain.values())))[0]
    rows = []
    for model in models:
        for position, class_name in enumerate(classes):
            rows.append([model if position == 0 else "", class_name]
                        + [_fmt_rate(half_rates.get((rain, model, class_name), math.nan)) for rain in rain_models])
    lines += _table(["Model", "Class"] + rain_models, rows)
    if len(rain_models) > 1:
        lines += ["", f"### {' vs '.join(rain_models)}: AP@0.5 by rate, side by side", ""]
        indexed = {rain: _index(records) for rain, records in records_by_rain.items()}
        rates = indexed[rain_models[0]][1]
        rows = []
        for model in models:
            for position, class_name in enumerate(classes):
                row = [model if position == 0 else "", class_name]
                for rate in rates:
                    row.append(" / ".join(_fmt(indexed[rain][3].get((model, rate, class_name), {}).get("ap50"))
                                          for rain in rain_models))
                rows.append(row)
        lines += _table(["Model", "Class"] + [_rate_label(r, rates[0]) for r in rates], rows)
    for what, by_rate in breakdowns.items():
        lines += ["", f"### AP@0.5 by {what}, {breakdown_model}, {paper_rain_model} rain", ""]
        rates = sorted(by_rate)
        bins = list(next(iter(by_rate.values())))
        rows = []
        for class_name in classes:
            for position, bin_label in enumerate(bins):
                row = [class_name if position == 0 else "", bin_label]
                for rate in rates:
                    entry = by_rate[rate][bin_label].get(class_name)
                    row.append("n/a" if entry is None or entry.n_gt == 0 else f"{_fmt(entry.ap50)} ({entry.n_gt})")
                rows.append(row)
        lines += _table(["Class", what.capitalize()] + [f"{r:g} mm/h" for r in rates], rows)
        lines += ["", "Cells: AP@0.5 (ground-truth boxes in the bin)."]
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------------------------
# Plots
# --------------------------------------------------------------------------------------------


def plot_metric_vs_rate(
    records: Sequence[Mapping[str, Any]],
    metric: str,
    out_png: str | Path,
    *,
    ci: bool = True,
    ylabel: str | None = None,
) -> Path:
    """Plot a metric against rainfall rate: one subplot per class, one line per model (Figs. 8-11).

    Args:
        records: Metric records with ``model``, ``rate``, ``class`` and ``metric`` keys.
        metric: Record key to plot, e.g. "ap50" or "f1".
        out_png: Output PNG path (parent folders created).
        ci: Shade ``<metric>_ci_low`` .. ``<metric>_ci_high`` where the records have them.
        ylabel: Y axis label; ``METRIC_LABELS[metric]`` (or the metric name) when None.

    Returns:
        The PNG path.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not records:
        raise ValueError("records: expected at least one metric record, got none")
    if metric not in records[0]:
        raise ValueError(f"metric: expected a record key such as 'ap50' or 'f1', got {metric!r}")
    models, rates, classes, by_key = _index(records)
    n_columns = min(len(classes), 4)
    n_rows = math.ceil(len(classes) / n_columns)
    figure = Figure(figsize=(3.6 * n_columns, 3.0 * n_rows), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.subplots(n_rows, n_columns, squeeze=False, sharey=True)
    default_colors = [f"C{i}" for i in range(10)]
    for position, class_name in enumerate(classes):
        axis = axes[position // n_columns][position % n_columns]
        for model_index, model in enumerate(models):
            color = PAPER_COLORS.get(model.lower(), default_colors[model_index % 10])
            rows = [by_key[(model, rate, class_name)] for rate in rates if (model, rate, class_name) in by_key]
            x = np.array([float(row["rate"]) for row in rows])
            y = np.array([_value(row.get(metric)) for row in rows])
            axis.plot(x, y, marker="o", markersize=3, color=color, label=model)
            low_key, high_key = f"{metric}_ci_low", f"{metric}_ci_high"
            if ci and rows and low_key in rows[0]:
                low = np.array([_value(row.get(low_key)) for row in rows])
                high = np.array([_value(row.get(high_key)) for row in rows])
                if np.any(np.isfinite(low)):
                    axis.fill_between(x, low, high, color=color, alpha=0.15, linewidth=0)
        axis.set_title(class_name)
        axis.set_xlabel("rainfall rate (mm/h)")
        axis.set_ylim(0, 1.02)
        axis.grid(alpha=0.3)
        if position % n_columns == 0:
            axis.set_ylabel(ylabel or METRIC_LABELS.get(metric, metric))
    for position in range(len(classes), n_rows * n_columns):
        axes[position // n_columns][position % n_columns].set_visible(False)
    axes[0][0].legend(fontsize=8)
    figure.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out_png, format="png")
    return out_png


def plot_detection_strip(
    images_by_rate: Mapping[float, np.ndarray],
    detections_by_rate: Mapping[float, Sequence[Mapping[str, Any]]],
    out_png: str | Path,
    *,
    class_names: Sequence[str] = CLASS_NAMES,
    min_score: float = 0.25,
    columns: int | None = None,
) -> Path:
    """Draw one frame across rain rates with its detections, tiled into one PNG (Fig. 12).

    Args:
        images_by_rate: ``{rate_mm_h: image}``, each image (H, W, 3) uint8 RGB, all the same shape.
        detections_by_rate: ``{rate_mm_h: records}``, COCO results records of that frame
            (bbox ``[x, y, w, h]`` in pixels, ``category_id`` a class id, ``score``); rates
            missing here are drawn without boxes.
        out_png: Output PNG path (parent folders created).
        class_names: ``class_names[category_id]`` labels the boxes.
        min_score: Detections below this confidence are not drawn.
        columns: Tiles per row; ``ceil(sqrt(n))`` when None.

    Returns:
        The PNG path.
    """
    import cv2

    if not images_by_rate:
        raise ValueError("images_by_rate: expected at least one {rate: image}, got none")
    rates = sorted(images_by_rate, key=float)
    first = np.asarray(images_by_rate[rates[0]])
    if first.ndim != 3 or first.shape[2] != 3 or first.dtype != np.uint8:
        raise ValueError(
            f"images_by_rate[{rates[0]}]: expected an (H, W, 3) uint8 RGB image, got {first.dtype} {first.shape}"
        )
    height, width = first.shape[:2]
    banner = 28
    tiles = []
    for rate in rates:
        image = np.asarray(images_by_rate[rate])
        if image.shape != first.shape or image.dtype != np.uint8:
            raise ValueError(
                f"images_by_rate[{rate}]: expected uint8 {first.shape} like the first image, got {image.dtype} {image.shape}"
            )
        tile = np.full((height + banner, width, 3), 255, dtype=np.uint8)
        tile[banner:] = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2BGR)
        cv2.putText(
            tile, f"{float(rate):g} mm/h", (6, banner - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 2, cv2.LINE_AA
        )
        for record in detections_by_rate.get(rate, ()):
            score = float(record["score"])
            if score < min_score:
                continue
            x, y, w, h = (float(v) for v in record["bbox"])
            class_id = int(record["category_id"])
            color = CLASS_COLOURS[class_id % len(CLASS_COLOURS)][::-1]  # BGR
            top_left = (int(round(x)), int(round(y)) + banner)
            bottom_right = (int(round(x + w)), int(round(y + h)) + banner)
            cv2.rectangle(tile, top_left, bottom_right, color, 2)
            name = class_names[class_id] if 0 <= class_id < len(class_names) else str(class_id)
            label = f"{name} {score:.2f}"
            (text_width, text_height), _ = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, 0.45, 1)
            label_top = max(banner, top_left[1] - text_height - 4)
            label_left = max(0, min(top_left[0], width - text_width - 2))
            cv2.rectangle(
                tile, (label_left, label_top), (label_left + text_width + 2, label_top + text_height + 4), color, -1
            )
            cv2.putText(
                tile,
                label,
                (label_left + 1, label_top + text_height + 1),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.45,
                (255, 255, 255),
                1,
                cv2.LINE_AA,
            )
        tiles.append(tile)
    n_columns = columns if columns is not None else math.ceil(math.sqrt(len(tiles)))
    if n_columns < 1:
        raise ValueError(f"columns: expected an int >= 1, got {columns!r}")
    n_rows = math.ceil(len(tiles) / n_columns)
    gap = 4
    canvas = np.full(
        (n_rows * (height + banner) + (n_rows - 1) * gap, n_columns * width + (n_columns - 1) * gap, 3),
        255,
        dtype=np.uint8,
    )
    for position, tile in enumerate(tiles):
        row, column = divmod(position, n_columns)
        top, left = row * (height + banner + gap), column * (width + gap)
        canvas[top : top + height + banner, left : left + width] = tile
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out_png), canvas):
        raise OSError(f"{out_png}: expected OpenCV to write a PNG, it reported failure")
    return out_png
