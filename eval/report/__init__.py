"""Reports of rainbench metric records (the seed paper's Tables I, III, IV and Figs. 8-12).

Modules:

- :mod:`.paper`: the seed paper's published numbers and presentation constants;
- :mod:`.records`: the record schema (one flat record per model, rate and class), the records of
  evaluations and robustness summaries, and ``metrics.json`` / ``metrics.csv`` I/O;
- :mod:`.markdown`: ``report.md`` of ``rainbench eval`` and of ``make paper`` (pure, return text);
- :mod:`.plots`: metric against rain rate (matplotlib);
- :mod:`.figures`: the detection strip (OpenCV);
- :mod:`.files`: write errors that name the file.
"""
