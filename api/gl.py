"""Choosing MuJoCo's offscreen OpenGL backend before ``mujoco`` is imported.

MuJoCo reads ``MUJOCO_GL`` once, when it is first imported. rainbench therefore decides the
backend just before MuJoCo is first imported: every rainbench module that needs MuJoCo writes
``from rainbench.gl import mujoco`` (this module's ``__getattr__``), which calls :func:`configure`
and then imports it. Importing ``rainbench``, ``rainbench.store``, ``rainbench.eval`` or the
configs in ``rainbench.gen.config`` chooses nothing:

- a ``MUJOCO_GL`` the user set is respected as it is (never overridden);
- otherwise ``egl`` if the EGL library is found, else ``osmesa`` if OSMesa is found;
- if neither is found, ``MUJOCO_GL`` stays unset and the first renderer raises
  :class:`GLBackendError`, naming the system packages to install.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
from collections.abc import Callable, MutableMapping
from types import SimpleNamespace

# backend -> (library name for ctypes.util.find_library, Debian/Ubuntu package that provides it)
BACKENDS: dict[str, tuple[str, str]] = {
    "egl": ("EGL", "libegl1"),
    "osmesa": ("OSMesa", "libosmesa6"),
}
AUTO_ORDER: tuple[str, ...] = ("egl", "osmesa")
VALID_VALUES: tuple[str, ...] = (*BACKENDS, "glfw")
"""The ``MUJOCO_GL`` values rainbench renders with: the offscreen backends, and ``glfw`` where a
display is set. MuJoCo knows others (``glx``, ``disable``, ...) that do not render offscreen."""
# Set by configure(): whether mujoco was already imported when rainbench chose the backend
# (then MuJoCo did not see the choice, and renderer errors say so).
state = SimpleNamespace(mujoco_imported_first=False)


class GLBackendError(RuntimeError):
    """No usable OpenGL backend for offscreen rendering."""


def missing_backend_message(tried: tuple[str, ...]) -> str:
    wanted = ", ".join(f"{name} (install {BACKENDS[name][1]})" for name in tried)
    return (
        f"no OpenGL backend for offscreen rendering: tried {wanted}; install one of these "
        "packages, or set MUJOCO_GL to a backend that works on this machine"
    )


def find_backend(
    requested: str | None = None,
    find_library: Callable[[str], str | None] | None = None,
) -> str:
    """The backend to use: ``requested`` if its library exists, else the first of egl, osmesa.

    Raises :class:`GLBackendError` naming the missing package(s) when none is found.
    """
    if requested is not None and requested not in BACKENDS:
        raise GLBackendError(
            f"GL backend: expected one of {', '.join(BACKENDS)}, got {requested!r}"
        )
    find_library = find_library or ctypes.util.find_library
    tried = (requested,) if requested else AUTO_ORDER
    for name in tried:
        if find_library(BACKENDS[name][0]):
            return name
    raise GLBackendError(missing_backend_message(tried))


def check_environment(
    environ: MutableMapping[str, str],
    find_library: Callable[[str], str | None] | None = None,
    rendering: bool = True,
) -> None:
    """Refuse a ``MUJOCO_GL`` set by the user that cannot render here, before mujoco is imported
    (importing it with ``MUJOCO_GL=osmesa`` and no OSMesa fails with an AttributeError deep in
    PyOpenGL; ``glfw`` without a display fails at the first render). One-line
    :class:`GLBackendError` naming the variable, what is missing and what works instead, and a
    ``PYOPENGL_PLATFORM`` of another backend (:func:`check_pyopengl_platform`). With
    ``rendering`` False (MuJoCo is needed but nothing is rendered: ``rainbench scene``), only
    what breaks the import is refused, not ``glfw`` without a display nor PyOpenGL's platform."""
    current = environ.get("MUJOCO_GL")
    find_library = find_library or ctypes.util.find_library
    working = [name for name in AUTO_ORDER if find_library(BACKENDS[name][0])]
    if not current:
        if working and rendering:  # the backend configure() will choose
            check_pyopengl_platform(environ, working[0])
        return
    instead = (f"set MUJOCO_GL={working[0]} (installed here) or unset MUJOCO_GL" if working
               else "; ".join(f"install {BACKENDS[n][1]} for {n}" for n in AUTO_ORDER))
    if current.strip().lower() not in VALID_VALUES:  # as MuJoCo reads it: case and spaces ignored
        shown = repr(current) if len(current) <= 40 else repr(current[:37]) + "..."
        raise GLBackendError(f"MUJOCO_GL: expected one of {', '.join(VALID_VALUES)} (glfw needs a "
                             f"display), got {shown}; {instead}")
    current = current.strip().lower()
    if current in BACKENDS and not find_library(BACKENDS[current][0]):
        raise GLBackendError(f"MUJOCO_GL={current}: the {BACKENDS[current][0]} library is not "
                             f"installed (package {BACKENDS[current][1]}); {instead}")
    if rendering and current == "glfw" and not (environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY")):
        raise GLBackendError(f"MUJOCO_GL=glfw: needs a display and DISPLAY is unset; rainbench "
                             f"renders offscreen: {instead}")
    if rendering:
        check_pyopengl_platform(environ, current)


def check_pyopengl_platform(environ: MutableMapping[str, str], backend: str) -> None:
    """Refuse a ``PYOPENGL_PLATFORM`` other than ``backend`` (``MUJOCO_GL`` as MuJoCo reads it,
    or the backend rainbench will choose where ``MUJOCO_GL`` is unset) for the offscreen
    backends: MuJoCo's EGL and OSMesa contexts need PyOpenGL on the same platform (MuJoCo
    compares it lower-cased), and otherwise fail at the first renderer with a message that
    blames a missing package; building and exporting scenes need no context and are not
    affected."""
    platform = environ.get("PYOPENGL_PLATFORM", "")
    backend = backend.strip().lower()
    if backend not in BACKENDS or not platform or platform.lower() == backend:
        return
    source = (f"MUJOCO_GL={backend}" if environ.get("MUJOCO_GL", "").strip()
              else f"the {backend} backend rainbench chose (MUJOCO_GL unset)")
    raise GLBackendError(f"PYOPENGL_PLATFORM={platform} conflicts with {source}: MuJoCo's "
                         f"{backend} rendering needs PyOpenGL on the same platform; unset "
                         f"PYOPENGL_PLATFORM or set it to {backend}")


def context_failure_message(backend: str, error: BaseException,
                            find_library: Callable[[str], str | None] | None = None,
                            environ: MutableMapping[str, str] | None = None) -> str:
    """One line for an OpenGL context that could not be made with ``MUJOCO_GL=backend`` (empty:
    unset): a missing library names its package; an installed one that failed says so, with
    MuJoCo's reason, instead of asking to install what is there."""
    find_library = find_library or ctypes.util.find_library
    environ = os.environ if environ is None else environ
    backend = backend.strip().lower()  # as MuJoCo reads it
    reason = " ".join(str(error).split()) or type(error).__name__
    shown = f"MUJOCO_GL={backend or 'unset'}"
    if backend == "glfw":
        display = environ.get("DISPLAY") or environ.get("WAYLAND_DISPLAY") or "unset"
        return (f"{shown}: no window could be opened on display {display} ({reason}); rainbench "
                "renders offscreen: unset MUJOCO_GL or set it to egl or osmesa")
    if backend in BACKENDS and find_library(BACKENDS[backend][0]):
        others = [name for name in AUTO_ORDER if name != backend and find_library(BACKENDS[name][0])]
        instead = f"try MUJOCO_GL={others[0]}" if others else (
            f"install {BACKENDS[[n for n in AUTO_ORDER if n != backend][0]][1]} for another backend")
        return (f"{shown}: the {BACKENDS[backend][0]} library is installed but no OpenGL context "
                f"could be made ({reason}); check the GPU driver or Mesa installation, or {instead}")
    tried = (backend,) if backend in BACKENDS else AUTO_ORDER
    return f"{missing_backend_message(tried)} ({shown}: {reason})"


def configure(
    environ: MutableMapping[str, str],
    find_library: Callable[[str], str | None] | None = None,
) -> str | None:
    """Set ``environ['MUJOCO_GL']`` when unset; returns the backend in force (None if none found)."""
    current = environ.get("MUJOCO_GL")
    if current:
        return current
    try:
        backend = find_backend(None, find_library)
    except GLBackendError:
        return None
    environ["MUJOCO_GL"] = backend
    state.mujoco_imported_first = "mujoco" in sys.modules
    return backend


def __getattr__(name: str):
    """``from rainbench.gl import mujoco``: the ``mujoco`` module, imported after :func:`configure`
    chose the backend from ``os.environ``. Every rainbench module that needs MuJoCo imports it
    this way, so the backend is chosen when MuJoCo is first needed (a scene is built or rendered),
    never by ``import rainbench``."""
    if name == "mujoco":
        configure(os.environ)
        try:
            import mujoco  # noqa: PLC0415
        except (AttributeError, ImportError, RuntimeError, OSError) as error:
            # A MUJOCO_GL that cannot work here fails deep in MuJoCo or PyOpenGL (and Python turns
            # an AttributeError raised here into "cannot import name 'mujoco'"): say why in one
            # line instead.
            check_environment(os.environ)
            reason = " ".join(str(error).split())
            raise GLBackendError(f"MUJOCO_GL={os.environ.get('MUJOCO_GL', '')}: importing mujoco "
                                 f"failed ({type(error).__name__}: {reason})") from None
        return mujoco
    raise AttributeError(f"module 'rainbench.gl' has no attribute {name!r}")
