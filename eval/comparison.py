"""The robustness comparison of models evaluated on one dataset: per model and class, AP@0.5 at
rate 0 and under rain, mPC and rPC with bootstrap intervals, and each model's paired mPC
difference from a reference model (a rain-trained model against the clean-trained one it
extends). :func:`rainbench.eval.pipeline.run_eval` writes these rows (``robustness.json``, a
section of ``report.md``) for every dataset with rate 0 and a rainy rate; ``make paper``'s report
and ``bench/quality.py --rain`` show them. Pure functions: nothing here reads or writes files.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from rainbench.store.classes import CLASS_NAMES, PAPER_CLASSES

from .metrics.bootstrap import robustness_intervals
from .metrics.coco import DEFAULT_BACKEND


def comparison_references(models: Sequence[str], chosen: Sequence[tuple[str, str]] = ()) -> dict[str, str]:
    """``{model: reference}`` for the robustness comparison of the evaluated ``models``.

    ``chosen`` (``(model, reference)`` pairs, ``--compare MODEL=REFERENCE``) wins; any other model
    is compared with the evaluated model whose name it extends by a ``-suffix`` (the longest such:
    ``rainbench-yolo11n-rain`` and ``rainbench-yolo11n-randomrain`` with ``rainbench-yolo11n``),
    in whatever order the models come; a model that extends none is compared with the first such
    model, which has no reference. Raises a one-line ValueError for a chosen name that is not
    among ``models``."""
    for pair in chosen:
        missing = [name for name in pair if name not in models]
        if missing:
            raise ValueError(f"--compare: {missing[0]!r} is not an evaluated model (models: {', '.join(models)})")
    bases = {model: [other for other in models if other != model and model.startswith(other + "-")]
             for model in models}
    anchor = next((model for model in models if not bases[model]), None)
    references = {}
    for model in models:
        if bases[model]:
            references[model] = max(bases[model], key=len)
        elif model != anchor:
            references[model] = anchor
    references.update(dict(chosen))
    return references


ROBUSTNESS_SEED = 0
"""Seed of the robustness comparison's frame resamples (the report is reproducible)."""


def comparison_rows(gt_dict: Mapping[str, Any], detections: Mapping[str, Mapping[float, Sequence[Mapping[str, Any]]]],
                    classes: Sequence[int] = PAPER_CLASSES, n_boot: int = 1000,
                    references: Mapping[str, str] | None = None, backend: str = DEFAULT_BACKEND) -> list[dict]:
    """Rows of the rain-robustness comparison of several models on one dataset.

    Per model (in the order of ``detections``) and class (ids ``classes``): AP@0.5 at rate 0, at
    50 mm/h (nan where not measured) and at the heaviest rate, mPC and rPC, each with its 95 %
    bootstrap interval, and the paired mPC difference from the model's reference, all from one set
    of ``n_boot`` frame resamples (:func:`rainbench.eval.metrics.bootstrap.robustness_intervals`,
    seed :data:`ROBUSTNESS_SEED`).

    Args:
        gt_dict: COCO ground-truth dict of the dataset's frames (the same at every rate).
        detections: ``{model: {rate_mm_h: COCO results records}}``, rates including 0 and one > 0.
        classes: Class ids.
        n_boot: Resamples.
        references: ``{model: reference model}`` (:func:`comparison_references`).
        backend: Metrics backend of the matching (:data:`rainbench.eval.metrics.coco.METRICS_BACKENDS`).

    Returns:
        Rows ``{model, class, n_gt, reference, heavy_rate}`` plus, for each of ``clean``,
        ``at_50``, ``at_heavy``, ``mpc``, ``rpc`` and ``mpc_difference``, the keys ``{key}``,
        ``{key}_low`` and ``{key}_high`` (nan where there is no value).
    """
    intervals = robustness_intervals(gt_dict, detections, n_boot, rng=np.random.default_rng(ROBUSTNESS_SEED),
                                     class_ids=classes, references=references, backend=backend)
    n_gt = {c: sum(1 for a in gt_dict["annotations"] if a["category_id"] == c and not a["iscrowd"]) for c in classes}
    rates = sorted(float(rate) for rate in next(iter(detections.values())))
    heavy = max(rates)
    nan = math.nan
    rows = []
    for model, by_class in intervals.items():
        for class_id in classes:
            entry = by_class[class_id]
            row: dict[str, Any] = {"model": model, "class": CLASS_NAMES[class_id], "n_gt": n_gt[class_id],
                                   "reference": entry.reference, "heavy_rate": heavy}
            for key, interval in (("clean", entry.ap50[0.0]), ("at_50", entry.ap50.get(50.0)),
                                  ("at_heavy", entry.ap50[heavy]), ("mpc", entry.mpc), ("rpc", entry.rpc),
                                  ("mpc_difference", entry.mpc_difference)):
                values = (nan, nan, nan) if interval is None else (interval.point, interval.low, interval.high)
                row.update(zip((key, f"{key}_low", f"{key}_high"), values))
            rows.append(row)
    return rows
