"""rainbench.mjcf: road scenes composed with MuJoCo's MjSpec (layouts, vehicles, people, lights).

Its modules import MuJoCo through :mod:`rainbench.gl`, which chooses the offscreen GL backend
first (a scene built here is rendered by :mod:`rainbench.gen` in the same process).
"""
