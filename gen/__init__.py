"""rainbench.gen: where datasets are written (MuJoCo simulation, offscreen rendering, labels from
segmentation, rain per rate, shards and the manifest through :mod:`rainbench.store`).

Its modules import MuJoCo through :mod:`rainbench.gl`, which chooses the offscreen GL backend
first.
"""
