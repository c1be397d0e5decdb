"""Detection metrics for rainbench: COCO AP, YOLO-style F1, robustness arithmetic, bootstrap CIs.

Everything here is a pure function of its arguments (no files, no plotting, no global random
state); the metric records, writing, rendering and plotting live in ``rainbench.eval.report``.

Modules:

- :mod:`.coco`: COCO inputs (``coco_ground_truth``, ``coco_detections``) and the one COCO
  set-up (``run_cocoeval``, through one of the ``METRICS_BACKENDS``), with the matches and AP
  read back as arrays (``match_table``, ``class_matches``, ``ap_per_iou``);
- :mod:`.matching`: COCOeval's bbox matching, vectorised (the "numpy" backend);
- :mod:`.accumulate`: COCO's interpolated AP for many weighted copies of the matches at once
  (``interpolated_ap``, ``image_weighted_ap``);
- :mod:`.f1`: YOLO-convention precision / recall / F1 from those matches;
- :mod:`.evaluation`: ``evaluate``, the per-class AP and F1 of one detection set (``ClassMetrics``);
- :mod:`.breakdown`: AP by object size and by visible fraction (``BreakdownAP``);
- :mod:`.robustness`: percent drop, mPC, rPC, half-value rate;
- :mod:`.bootstrap`: percentile bootstrap intervals of AP over frames (``BootstrapCI``).

Conventions (fixed by the project):

- Class ids are COCO-80 indices: 0 person, 1 bicycle, 2 car, 3 motorcycle, 5 bus, 7 truck
  (``CLASS_NAMES[i]`` is the name of class id ``i``, :mod:`rainbench.store.classes`; 4 airplane and
  6 train are never labelled). The paper's four classes 0..3 are evaluated by default
  (``PAPER_CLASSES``). COCO category ids are the same numbers, *including 0*:
  pycocotools handles category id 0 (it indexes categories by value and never tests them for
  truth), which the tests pin against a direct ``loadRes``/``COCOeval`` run.
- Dataset boxes are float32 ``x1, y1, x2, y2`` in pixel-edge coordinates (a box covering pixel
  columns 0..9 is ``x1=0, x2=10``); COCO boxes are ``[x, y, w, h]`` with ``w = x2 - x1``.
- Image ids are positive ints. COCO annotation ids must be >= 1, because COCOeval stores the
  matched ground-truth id in ``dtMatches`` and treats 0 as "unmatched".
- Detections are COCO results records ``{"image_id": int, "category_id": int,
  "bbox": [x, y, w, h], "score": float in [0, 1]}``.
- Rates are rainfall rates in mm/h (0, 10, ..., 100); rate 0 is the clean ("Normal") condition.

AP is COCO's: bbox IoU, maxDets 100, area range "all", the 101-point interpolated precision at
IoU 0.50 (AP50), 0.75 (AP75) and averaged over 0.50:0.05:0.95 (AP50-95). Two backends compute it
(``METRICS_BACKENDS``, ``rainbench eval --metrics``): "numpy" (the default), a vectorised
re-implementation of ``COCOeval.evaluate`` (:mod:`.matching`) and ``accumulate``
(:mod:`.accumulate`), and "pycocotools", pycocotools' ``COCOeval`` itself, the reference. They
give identical matches and the same AP (the tests hold every figure equal to 1e-9 on crafted
data; it is bit for bit in practice). Precision/recall/F1 follow the YOLO (ultralytics
``ap_per_class``) convention, fed with the TP/FP matches at IoU 0.5 (COCO's ``evalImgs``). The
bootstrap re-uses those per-image matches and re-computes COCO's interpolated AP for every
resample at once (:func:`.accumulate.image_weighted_ap`), bit for bit the per-resample
computation, which the tests check against COCOeval and a per-copy loop.
"""
