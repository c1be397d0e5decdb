"""Plots of metric records against rain rate (the seed paper's Figs. 8-11), drawn with matplotlib's
Agg canvas (no pyplot state, no display, bundled DejaVu fonts only). matplotlib is imported when a
plot is drawn, not with this module.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from rainbench.store.images import file_error
from .paper import PAPER_COLORS
from .records import as_float, index_records, is_missing

METRIC_LABELS: dict[str, str] = {
    "ap50": "AP@0.5",
    "ap75": "AP@0.75",
    "ap50_95": "AP@0.5:0.95",
    "f1": "F1",
    "f1_at_conf": "F1 @ conf",
}
"""Axis labels of record metrics."""


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
    models, rates, classes, by_key = index_records(records)
    n_columns = min(len(classes), 4)
    n_rows = math.ceil(len(classes) / n_columns)
    figure = Figure(figsize=(3.6 * n_columns, 3.0 * n_rows), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.subplots(n_rows, n_columns, squeeze=False, sharex=True, sharey=True)
    default_colors = [f"C{i}" for i in range(10)]
    for position, class_name in enumerate(classes):
        axis = axes[position // n_columns][position % n_columns]
        for model_index, model in enumerate(models):
            color = PAPER_COLORS.get(model.lower(), default_colors[model_index % 10])
            rows = [by_key[(model, rate, class_name)] for rate in rates if (model, rate, class_name) in by_key]
            x = np.array([float(row["rate"]) for row in rows])
            y = np.array([as_float(row.get(metric)) for row in rows])
            axis.plot(x, y, marker="o", markersize=3, color=color, label=model)
            low_key, high_key = f"{metric}_ci_low", f"{metric}_ci_high"
            if ci and rows and low_key in rows[0]:
                low = np.array([as_float(row.get(low_key)) for row in rows])
                high = np.array([as_float(row.get(high_key)) for row in rows])
                if np.any(np.isfinite(low)):
                    axis.fill_between(x, low, high, color=color, alpha=0.15, linewidth=0)
        plotted = [as_float(row.get(metric)) for model in models for rate in rates
                   for row in [by_key.get((model, rate, class_name))] if row is not None]
        if not any(math.isfinite(value) for value in plotted):
            # an empty panel reads as a plotting fault: say why it is empty
            labelled = sum(int(row["n_gt"]) for key, row in by_key.items()
                           if key[2] == class_name and not is_missing(row.get("n_gt")))
            reason = "no labelled boxes" if labelled == 0 else "no values"
            axis.text(0.5, 0.5, f"{reason}\nof this class", transform=axis.transAxes,
                      ha="center", va="center", color="0.4", fontsize=9)
        axis.set_title(class_name)
        axis.set_xlabel("rainfall rate (mm/h)")
        axis.set_ylim(0, 1.02)
        axis.grid(alpha=0.3)
        if position % n_columns == 0:
            axis.set_ylabel(ylabel or METRIC_LABELS.get(metric, metric))
    for position in range(len(classes), n_rows * n_columns):
        axes[position // n_columns][position % n_columns].set_visible(False)
    for position in range(len(classes)):  # sharex hides the rates on all but the bottom row
        axes[position // n_columns][position % n_columns].xaxis.set_tick_params(labelbottom=True)
    axes[0][0].legend(fontsize=8)
    figure.tight_layout()
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    try:
        figure.savefig(out_png, format="png")
    except OSError as error:
        raise file_error(error, out_png) from error
    return out_png
