"""rainbench.mjcf: road scenes composed with MuJoCo's MjSpec (layouts, vehicles, people, lights).

Importing it chooses MuJoCo's offscreen GL backend (:func:`rainbench.gl.configure`) before any of
its modules imports mujoco: a scene built here is rendered by :mod:`rainbench.gen` in the same
process.
"""

import os as _os

from rainbench import gl as _gl

GL_BACKEND = _gl.configure(_os.environ)
