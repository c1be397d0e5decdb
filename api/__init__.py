"""rainbench: synthetic MuJoCo driving datasets with calibrated rain, and a YOLO evaluator.

Importing rainbench chooses MuJoCo's offscreen GL backend (see :mod:`rainbench.gen.gl`) before
any rainbench module imports mujoco.
"""

import os as _os

from rainbench.gen import gl as _gl

GL_BACKEND = _gl.configure(_os.environ)

__version__ = "0.1.0"
