"""Markdown reports of metric records: ``report.md`` of ``rainbench eval`` (:func:`render_report_md`)
and of ``make paper`` (:func:`render_paper_md`), in the seed paper's table layout (Tables I, III
and IV). Pure functions: they return text and write nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

from rainbench.eval.metrics.robustness import percent_drop

from .paper import PAPER_TABLE_I, PAPER_TABLES, TABLE_CLASS_ORDER
from .records import as_float, index_records, is_missing, robustness_records

def _fmt(value: Any) -> str:
    """Metric cell: 3 decimals, 2 significant digits below 0.01 (the paper's 0.0043), n/a for nan."""
    number = as_float(value)
    if math.isnan(number):
        return "n/a"
    if number != 0 and abs(number) < 0.01:
        return f"{number:.2g}"
    return f"{number:.3f}"


def _fmt_pct(value: Any) -> str:
    """Percent cell with 2 decimals, n/a for nan."""
    number = as_float(value)
    return "n/a" if math.isnan(number) else f"{number:.2f}"


def _rate_label(rate: float, clean_rate: float) -> str:
    """'Normal' for the clean rate 0, else e.g. '100mm/h' (the paper's labels); a dataset without
    rate 0 compares with its lowest rate, '50mm/h (lowest)'."""
    if rate != clean_rate:
        return f"{rate:g}mm/h"
    return "Normal" if rate == 0 else f"{rate:g}mm/h (lowest)"


def _table(header: Sequence[str], rows: Sequence[Sequence[str]]) -> list[str]:
    """Markdown table lines."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


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
    paper column beside each class the paper reports, when an evaluated model is one of the
    paper's; otherwise the paper's models follow as rows of their own, ``YOLOv4 (paper)``)."""
    paper_metric = (paper or {}).get(metric)
    paper_classes = {name for by_rate in (paper_metric or {}).values() for values in by_rate.values()
                     for name in values}
    if paper_metric is not None and not any(_paper_model(model, paper_metric, paper_models) for model in models):
        # none of ours is the paper's: its models as rows below ours, not columns of n/a
        return _degradation_table(metric, models, classes, by_key, clean_rate, heavy_rate, None, None) + [
            row for name in paper_metric
            for row in _paper_rows(name, paper_metric[name], classes, clean_rate, heavy_rate)]
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
                clean = as_float(by_key.get((model, clean_rate, class_name), {}).get(metric))
                if rate is None:
                    row.append(
                        _fmt_pct(
                            percent_drop(clean, as_float(by_key.get((model, heavy_rate, class_name), {}).get(metric)))
                        )
                    )
                else:
                    row.append(_fmt(by_key.get((model, rate, class_name), {}).get(metric)))
                if class_name in paper_classes:
                    published_clean = paper_rates.get(clean_rate, {}).get(class_name)
                    if rate is None:
                        published_heavy = paper_rates.get(heavy_rate, {}).get(class_name)
                        row.append(_fmt_pct(percent_drop(as_float(published_clean), as_float(published_heavy))))
                    else:
                        row.append(_fmt(paper_rates.get(rate, {}).get(class_name)))
            rows.append(row)
    return _table(header, rows)


def _paper_rows(name: str, by_rate: Mapping[float, Mapping[str, Any]], classes: Sequence[str],
                clean_rate: float, heavy_rate: float) -> list[str]:
    """Table lines of one of the paper's models (``<name> (paper)``: Normal, the heavy rate, %
    drop) in the columns ``classes``; n/a where the paper has no value."""
    lines = []
    for position, rate in enumerate((clean_rate, heavy_rate, None)):
        row = [f"{name} (paper)" if position == 0 else "",
               _rate_label(rate, clean_rate) if rate is not None else "% drop"]
        for class_name in classes:
            published_clean = by_rate.get(clean_rate, {}).get(class_name)
            if rate is None:
                row.append(_fmt_pct(percent_drop(as_float(published_clean),
                                                 as_float(by_rate.get(heavy_rate, {}).get(class_name)))))
            else:
                row.append(_fmt(by_rate.get(rate, {}).get(class_name)))
        lines.append("| " + " | ".join(row) + " |")
    return lines


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
    robustness: Sequence[Mapping[str, Any]] = (),
    ignore_regions: Mapping[str, int] | bool | None = None,
    scored_labels: str | None = None,
) -> str:
    """Render records as a markdown report in the paper's layout.

    Sections: Table III (AP@0.5) and Table IV (F1 at the YOLO best-F1 confidence) with rows
    model x {Normal, heavy rate, % drop} and columns the records' classes (car / person / bicycle
    / motorcycle in the paper's order, then e.g. bus / truck; a paper column beside the paper's); the
    full rate-by-rate tables of AP@0.5, AP@0.5:0.95 and F1; the 95 % bootstrap intervals of
    AP@0.5 (when the records carry them); mPC / rPC (Michaelis et al. 2019); ground-truth counts.

    Args:
        records: Records of :func:`rainbench.eval.report.records.metric_records` (or read back by
            :func:`rainbench.eval.report.records.read_metrics`).
        paper: Published numbers to put beside ours, e.g.
            :data:`rainbench.eval.report.paper.PAPER_TABLES`
            (``{metric: {model: {rate: {class: value}}}}``); None leaves them out.
        paper_models: ``{our model name: paper model name}``; without it a model is matched to
            the paper's by case-insensitive name.
        clean_rate: Rate shown as "Normal".
        heavy_rate: Rate compared with Normal in Tables III/IV; the highest rate when None.
        title: Report title.
        robustness: Rows of :func:`rainbench.eval.comparison.comparison_rows` (mPC and rPC with
            intervals, paired differences); none: no such section.
        ignore_regions: ``{class name: ignore regions in the ground truth}`` (a sentence under
            the ground-truth counts); False: they were left out of the scoring (said so); None:
            nothing said.
        scored_labels: The labels scored as targets in words (``TargetFilter.describe``), when
            not every label was; the others are counted among the ignore regions.

    Returns:
        The markdown text.
    """
    if not records:
        raise ValueError("records: expected at least one metric record, got none")
    models, rates, classes, by_key = index_records(records)
    heavy = max(rates) if heavy_rate is None else float(heavy_rate)
    if heavy not in rates or float(clean_rate) not in rates:
        raise ValueError(
            f"clean_rate/heavy_rate: expected rates present in the records {rates}, got {clean_rate} and {heavy}"
        )
    clean_rate = float(clean_rate)
    lines = [f"# {title}", ""]
    lines += [
        f"Models: {', '.join(models)}. Rates: {', '.join(f'{r:g}' for r in rates)} mm/h. "
        "AP is COCO's 101-point interpolated AP (pycocotools' definition, maxDets 100); F1, precision and recall "
        "are taken at the confidence maximising the mean F1 over classes (YOLO convention). "
        f"% drop = 100 ({'Normal' if clean_rate == 0 else 'lowest rate'} - rain) / "
        f"{'Normal' if clean_rate == 0 else 'lowest rate'}.",
        "",
    ]
    baseline, heavy_label = _rate_label(clean_rate, clean_rate), _rate_label(heavy, clean_rate)
    if clean_rate != 0:
        lines += [f"The dataset has no rate 0 (no clean frames): the tables compare with its lowest rate, "
                  f"{clean_rate:g} mm/h, in place of Normal.", ""]
    if heavy == clean_rate:
        lines += ["## Tables III and IV", "", f"One rate only ({heavy_label}): no degradation to show."]
    else:
        lines += [f"## Table III. AP@0.5 degradation, {baseline} vs {heavy_label}", ""]
        lines += _degradation_table("ap50", models, classes, by_key, clean_rate, heavy, paper, paper_models)
        lines += ["", f"## Table IV. F1 degradation, {baseline} vs {heavy_label}", ""]
        lines += _degradation_table("f1", models, classes, by_key, clean_rate, heavy, paper, paper_models)
    if paper is not None and set(classes) & set(TABLE_CLASS_ORDER) and heavy != clean_rate:
        lines += ["", "(paper): the seed paper's published values (Tables III and IV, CARLA Town04, "
                      "COCO-trained detectors), for reference: beside a model of the same name, else "
                      "as rows of their own."]
    for metric, label in (("ap50", "AP@0.5"), ("ap50_95", "AP@0.5:0.95"), ("f1", "F1")):
        lines += ["", f"## {label} by rainfall rate", ""]
        lines += _rate_table(metric, models, rates, classes, by_key, clean_rate, lambda r, m=metric: _fmt(r.get(m)))
    has_ci = any(not is_missing(record.get("ap50_ci_low")) for record in records)
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
                if is_missing(r.get("ap50_ci_low"))
                else f"[{_fmt(r.get('ap50_ci_low'))}, {_fmt(r.get('ap50_ci_high'))}]"
            ),
        )
    lines += ["", "## Robustness: mPC (mean over rates > 0) and rPC = mPC / Normal", ""]
    has_clean = 0.0 in rates
    if not has_clean:
        lines += ["mPC and rPC need clean frames (rate 0); this dataset has none."]
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
    if has_clean:
        lines += _table(header, rows)
    if robustness:
        lines += [""] + robustness_section({"": robustness}, level="##")
    lines += ["", f"## Ground-truth instances (non-ignored), model {models[0]}", ""]
    lines += _table(
        ["Class"] + [_rate_label(rate, clean_rate) for rate in rates],
        [
            [class_name]
            + [
                "n/a"
                if is_missing(by_key.get((models[0], rate, class_name), {}).get("n_gt"))
                else str(int(by_key[(models[0], rate, class_name)]["n_gt"]))
                for rate in rates
            ]
            for class_name in classes
        ],
    )
    if scored_labels is not None:
        lines += ["", f"Scored labels: {scored_labels}; the other labels are ignore regions of the scoring "
                      "(`--min-height`, `--min-visible`, `--max-truncation`)."]
    if ignore_regions is False:
        lines += ["", "Ignore regions were left out (`--no-ignore-regions`): detections of actors too small "
                      "or hidden to be labels count as false positives."]
    elif ignore_regions is not None:
        counts = ", ".join(f"{name} {ignore_regions.get(name, 0)}" for name in classes)
        which = "actors too small or hidden to be labels" + ("" if scored_labels is None else ", and the labels not scored")
        lines += ["", f"Ignore regions ({which}; COCO crowd boxes: a detection "
                      f"of one is neither right nor wrong, docs/eval.md): {counts}."]
    return "\n".join(lines) + "\n"


def _fmt_rate(value: float) -> str:
    """Rate cell of the half-value table: '> max rate' for inf, n/a for nan, else whole mm/h."""
    if math.isinf(value):
        return "> max rate"
    return "n/a" if math.isnan(value) else f"{value:.0f}"


def _weather_share(records_by_rain: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[str]:
    """Section comparing physical rain with and without the weather following the rate."""
    fixed = [name for name in records_by_rain if name.endswith("-fixed-weather")]
    if not fixed or fixed[0].removesuffix("-fixed-weather") not in records_by_rain:
        return []
    follows = fixed[0].removesuffix("-fixed-weather")
    models, rates, classes, with_weather = index_records(records_by_rain[follows])
    _, _, _, without = index_records(records_by_rain[fixed[0]])
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
             f"weather - AP loss without) / AP loss with the weather, at {_rate_label(heavy, clean)}. "
             "The two effects do not add: a negative share means the rain over the unchanged base "
             "weather cost more than the rain in its own weather (in daylight the rain's haze takes "
             "the bright base sky's colour and washes out the frame, where the weather that follows "
             "the rate darkens the sky and the camera's exposure brings the scene back).", ""]
    lines += _table(["Model", "Class", "AP@0.5 Normal", f"{heavy:g} mm/h, weather follows",
                     f"{heavy:g} mm/h, fixed weather", "Share of the loss from the weather"], rows)
    return lines + [""]


def _with_interval(row: Mapping[str, Any], key: str) -> str:
    """``0.812 (0.770-0.850)``: a point and its interval, n/a for nan."""
    point, low, high = (as_float(row[f"{key}{suffix}"]) for suffix in ("", "_low", "_high"))
    if math.isnan(point):
        return "n/a"
    return f"{_fmt(point)} ({_fmt(low)}-{_fmt(high)})" if not math.isnan(low) else _fmt(point)


def _signed_interval(row: Mapping[str, Any], key: str) -> str:
    """``+0.087 (+0.041 to +0.127)``: a signed difference and its interval, blank for nan."""
    point, low, high = (as_float(row[f"{key}{suffix}"]) for suffix in ("", "_low", "_high"))
    if math.isnan(point):
        return ""
    return f"{point:+.3f} ({low:+.3f} to {high:+.3f})" if not math.isnan(low) else f"{point:+.3f}"


def _in_table_class_order(rows: Sequence[Mapping[str, Any]]) -> list[Mapping[str, Any]]:
    """``rows`` (``model``, ``class`` keys) with each model's rows in the tables' class order
    (:func:`~rainbench.eval.report.records.index_records`: the paper's order, then class ids),
    models in their first-appearance order."""
    models = list(dict.fromkeys(row["model"] for row in rows))
    classes = index_records([{**row, "rate": 0.0} for row in rows])[2]
    return sorted(rows, key=lambda row: (models.index(row["model"]), classes.index(row["class"])))


def robustness_section(robustness: Mapping[str, Sequence[Mapping[str, Any]]], level: str = "###") -> list[str]:
    """Section comparing models' robustness with intervals, one table per dataset.

    Args:
        robustness: ``{dataset name: rows}``, rows of :func:`rainbench.eval.comparison.comparison_rows`;
            an empty name prints no name line (one dataset).
        level: The heading's markdown level.

    Returns:
        Markdown lines (none when ``robustness`` is empty).
    """
    if not robustness:
        return []
    lines = [f"{level} Rain robustness with intervals: clean-trained and rain-trained models compared", "",
             "mPC: mean AP@0.5 over the rainy rates; rPC = mPC / AP@0.5 Normal (Michaelis et al. 2019). "
             "Intervals: 95 % percentile bootstrap over frames, one set of resamples for every rate and "
             "every model, so each model's mPC difference from its reference (the model whose name it "
             "extends, `rainbench-yolo11n-rain` from `rainbench-yolo11n`, else the first model that extends none) is paired: "
             "an interval that excludes 0 is a difference these frames support. Evaluate a clean-trained "
             "model with its rain-trained variants together to compare them (docs/models.md).", ""]
    for name, rows in robustness.items():
        if not rows:
            continue
        heavy = as_float(rows[0]["heavy_rate"])
        lines += [f"{name}:", ""] if name else []
        table_rows = []
        previous = None
        for row in _in_table_class_order(rows):
            model = row["model"] if row["model"] != previous else ""
            previous = row["model"]
            reference = row.get("reference")
            difference = _signed_interval(row, "mpc_difference")
            table_rows.append([model, row["class"], str(row["n_gt"]), _with_interval(row, "clean"),
                               _fmt(row["at_50"]), _with_interval(row, "at_heavy"), _with_interval(row, "mpc"),
                               _with_interval(row, "rpc"),
                               f"{difference} vs {reference}" if difference and reference else ""])
        lines += _table(["Model", "Class", "Boxes", "AP@0.5 Normal", "50 mm/h", f"{heavy:g} mm/h", "mPC", "rPC",
                         "mPC difference (paired)"], table_rows)
        lines += [""]
    return lines


def render_paper_md(
    *,
    setup_lines: Sequence[str],
    table_one: Mapping[str, tuple[int, int]],
    records_by_rain: Mapping[str, Sequence[Mapping[str, Any]]],
    half_rates: Mapping[tuple[str, str, str], float],
    breakdowns: Mapping[str, Mapping[float, Mapping[str, Mapping[str, Any]]]],
    breakdown_model: str,
    paper_rain_model: str = "jeon2022",
    robustness: Mapping[str, Sequence[Mapping[str, Any]]] | None = None,
) -> str:
    """The ``make paper`` report: our Tables I, III and IV beside the seed paper's, plots of both
    rain models, and the analyses beyond the paper. Every table shows the classes of the records
    (the evaluated ones: by default the paper's four; bus and truck when asked for), in the
    paper's order, then the others in class-id order; the paper's columns read n/a for classes it
    did not have.

    Args:
        setup_lines: Markdown lines describing the run (data, models, hardware, times).
        table_one: ``{class: (objects, instances)}`` of our dataset (a missing class counts 0).
        records_by_rain: ``{rain model: metric records}`` (:func:`.records.metric_records`), each
            with the plots ``<rain model>/ap50_vs_rate.png`` and ``f1_vs_rate.png`` beside the report.
        half_rates: ``{(rain model, model, class): rate}`` where AP@0.5 falls to half its clean
            value (inf: never within the measured rates).
        breakdowns: ``{"visible fraction" | "box size": {rate: {bin: {class: BreakdownAP}}}}`` of
            ``breakdown_model`` under ``paper_rain_model`` rain.
        breakdown_model: The model of ``breakdowns``.
        paper_rain_model: The rain model of the paper's Tables III and IV comparison.
        robustness: ``{rain model: rows}`` of :func:`robustness_section` (none: no such section).

    Returns:
        The markdown text.
    """
    lines = ["# rainbench: the seed paper's experiment on rainbench data", ""]
    lines += list(setup_lines) + [""]
    classes = index_records(next(iter(records_by_rain.values())))[2] if records_by_rain else list(TABLE_CLASS_ORDER)
    lines += ["## Table I. Objects and instances per class", ""]
    rows = []
    for class_name in classes:
        ours = table_one.get(class_name, (0, 0))
        paper = [str(v) for v in PAPER_TABLE_I[class_name]] if class_name in PAPER_TABLE_I else ["n/a", "n/a"]
        rows.append([class_name, str(ours[0]), str(ours[1]), *paper])
    lines += _table(["Class", "Objects", "Instances", "Objects (paper)", "Instances (paper)"], rows)
    for rain_model, records in records_by_rain.items():
        models, rates, rain_classes, by_key = index_records(records)
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
    lines += robustness_section(robustness or {})
    lines += ["### Rain rate (mm/h) at which AP@0.5 falls to half its clean value", ""]
    rain_models = list(records_by_rain)
    models = index_records(next(iter(records_by_rain.values())))[0]
    rows = []
    for model in models:
        for position, class_name in enumerate(classes):
            rows.append([model if position == 0 else "", class_name]
                        + [_fmt_rate(half_rates.get((rain, model, class_name), math.nan)) for rain in rain_models])
    lines += _table(["Model", "Class"] + rain_models, rows)
    if len(rain_models) > 1:
        lines += ["", f"### {' vs '.join(rain_models)}: AP@0.5 by rate, side by side", ""]
        indexed = {rain: index_records(records) for rain, records in records_by_rain.items()}
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
        caption = "Cells: AP@0.5 (ground-truth boxes in the bin)."
        if what == "visible fraction":
            # a detection matching no label has no visible fraction: it is left out of every bin
            caption += (" Detections that match no label are left out of every bin (they have no "
                        "visible fraction), so these APs count no false positives: they measure how "
                        "well the labels of a bin are found and ranked, are higher than the overall "
                        "AP and are not comparable with it or with the box-size table, which counts "
                        "false positives as COCO's area ranges do.")
        lines += ["", caption]
    return "\n".join(lines) + "\n"
