"""rainbench: synthetic MuJoCo driving datasets with calibrated rain, and a YOLO evaluator.

Importing rainbench chooses MuJoCo's offscreen GL backend (see :mod:`rainbench.gen.gl`) before
any rainbench module imports mujoco.
"""

import os as _os

from rainbench.gen import gl as _gl

GL_BACKEND = _gl.configure(_os.environ)

__version__ = "0.1.0"


def __getattr__(name):
    """Lazy public API: ``from rainbench import ShardDataset, ShardReader`` (imports torch)."""
    if name in ("ShardDataset", "ShardReader"):
        from rainbench.gen import reader

        return getattr(reader, name)
    raise AttributeError(f"module 'rainbench' has no attribute {name!r}")
