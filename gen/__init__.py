"""rainbench.gen: where datasets are written (MuJoCo simulation, offscreen rendering, labels from
segmentation, rain per rate, shards and the manifest through :mod:`rainbench.store`).

Importing it chooses MuJoCo's offscreen GL backend (:func:`rainbench.gl.configure`) before any of
its modules imports mujoco.
"""

import os as _os

from rainbench import gl as _gl

GL_BACKEND = _gl.configure(_os.environ)
