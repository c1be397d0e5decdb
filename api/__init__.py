"""rainbench: synthetic MuJoCo driving datasets with calibrated rain, and a YOLO evaluator.

Importing rainbench chooses nothing and imports neither MuJoCo nor OpenGL: the offscreen GL
backend is chosen (:mod:`rainbench.gl`) just before MuJoCo is first imported, by the modules that
build or render scenes.
"""

__version__ = "0.1.0"


def __getattr__(name):
    """Lazy public API: ``from rainbench import ShardDataset, ShardReader`` (the first imports
    torch)."""
    if name in ("ShardDataset", "ShardReader"):
        from rainbench import store

        return getattr(store, name)
    raise AttributeError(f"module 'rainbench' has no attribute {name!r}")
