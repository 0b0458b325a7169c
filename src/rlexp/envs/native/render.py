"""Offscreen RGB frames of one env with ``mujoco.Renderer`` and a free camera placed by eye/target/up.

The OpenGL backend is chosen when ``rlexp.envs.native`` is imported, before MuJoCo is: ``MUJOCO_GL``
if set, else EGL when libEGL is found, else OSMesa (software) when libOSMesa is found. Debian
packages: ``libegl1`` (+ a Mesa driver: ``libegl-mesa0``, ``libgl1-mesa-dri``) for EGL, or
``libosmesa6`` for OSMesa.
"""

from __future__ import annotations

import ctypes.util
import math
import os
import platform
import sys
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import mujoco


def choose_gl_backend() -> str | None:
    """Set ``MUJOCO_GL`` (if unset) to egl, else osmesa, whichever library is installed."""
    if os.environ.get("MUJOCO_GL"):
        return os.environ["MUJOCO_GL"]
    for backend, lib in (("egl", "EGL"), ("osmesa", "OSMesa")):
        if ctypes.util.find_library(lib):
            os.environ["MUJOCO_GL"] = backend
            if backend == "osmesa":
                os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
            return backend
    return None


#: MUJOCO_GL values (as MuJoCo reads them: lower case, stripped) that turn rendering off, and those
#: that render through a window system (GLFW, GLX: they need a display); egl and osmesa need none.
GL_OFF = ("disable", "disabled", "off", "false", "0")
GL_WINDOWED = ("", "enable", "enabled", "on", "true", "1", "glfw", "glx")
GL_HEADLESS = ("egl", "osmesa")
GL_FIX = "use MUJOCO_GL=egl (Debian: libegl1 libegl-mesa0) or MUJOCO_GL=osmesa (libosmesa6)"


def effective_gl_backend() -> str:
    """The MUJOCO_GL value MuJoCo renders with: the one it read when it was imported, else the one
    it will read (chosen by ``choose_gl_backend`` if unset)."""
    gl_context = sys.modules.get("mujoco.rendering.classic.gl_context")
    if gl_context is not None and isinstance(getattr(gl_context, "_MUJOCO_GL", None), str):
        return gl_context._MUJOCO_GL
    choose_gl_backend()
    return os.environ.get("MUJOCO_GL", "").lower().strip()


def gl_problem(rendering: bool = True) -> str | None:
    """Why offscreen rendering cannot work in this process (None: it may; rendering one frame tells
    for sure). ``rendering=False``: only what makes ``import mujoco`` itself fail (a MUJOCO_GL value
    MuJoCo does not know, or egl/osmesa without its library), which breaks every MuJoCo env. Reads
    the environment and tries to load the backend's libraries; imports nothing."""
    if platform.system() != "Linux":
        return None
    value = effective_gl_backend()
    shown = f"MUJOCO_GL={value!r}" if value else "MUJOCO_GL unset (GLFW)"
    if value not in GL_OFF + GL_WINDOWED + GL_HEADLESS:
        return (
            f"{shown} is not a MuJoCo GL backend (MuJoCo accepts {list(GL_HEADLESS)} or glfw/glx)"
        )
    missing = _missing_library(value)
    if missing is not None:  # import mujoco would die in PyOpenGL (AttributeError, a traceback)
        return f"{shown} needs lib{missing}, which cannot be loaded here{_working()}"
    if not rendering:
        return None
    if value in GL_OFF:
        return f"{shown} turns rendering off"
    display = os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    if value in GL_WINDOWED and not display:
        return f"{shown} renders through a window system and DISPLAY is not set"
    return None


#: The libraries each headless backend loads through PyOpenGL (any one name of each group).
GL_LIBRARIES = {"egl": (("EGL",), ("OpenGL", "GL")), "osmesa": (("OSMesa",),)}


def _loads(name: str) -> bool:
    """``lib<name>.so`` (or a versioned one) can be loaded, as PyOpenGL looks for it."""
    for filename in (f"lib{name}.so", *(f"lib{name}.so.{i}" for i in range(9, -1, -1))):
        try:
            ctypes.CDLL(filename, mode=ctypes.RTLD_GLOBAL)
            return True
        except OSError:
            continue
    return False


def _missing_library(value: str) -> str | None:
    """The library a headless ``MUJOCO_GL`` value needs and this machine lacks (None: none is
    missing, or MuJoCo is already imported and rendering with it)."""
    if "mujoco.rendering.classic.gl_context" in sys.modules:
        return None
    for group in GL_LIBRARIES.get(value, ()):
        if not any(_loads(name) for name in group):
            return group[0]
    return None


def _working() -> str:
    """The MUJOCO_GL values that can work on this machine, for a message."""
    ok = [value for value in GL_LIBRARIES if all(any(map(_loads, g)) for g in GL_LIBRARIES[value])]
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        ok.append("glfw")
    return f"; MUJOCO_GL values that work here: {', '.join(ok) or 'none (install one below)'}"


def _renderer(
    model: mujoco.MjModel,
    renderers: dict[tuple[int, int], mujoco.Renderer],
    width: int,
    height: int,
) -> mujoco.Renderer:
    """The renderer of ``width`` x ``height`` frames, made once and kept in ``renderers``."""
    import mujoco

    key = (width, height)
    if key not in renderers:
        try:
            renderers[key] = mujoco.Renderer(model, height=height, width=width)
        except Exception as exc:  # GL context creation failures come as several types
            raise RuntimeError(
                f"offscreen rendering failed with MUJOCO_GL={os.environ.get('MUJOCO_GL')!r}: {exc}. "
                "Install libegl1 + libegl-mesa0 (MUJOCO_GL=egl) or libosmesa6 (MUJOCO_GL=osmesa) and "
                "set MUJOCO_GL before anything imports mujoco."
            ) from exc
    return renderers[key]


def render_frame(
    model: mujoco.MjModel,
    renderers: dict[tuple[int, int], mujoco.Renderer],
    asset: str,
    data: mujoco.MjData,
    width: int,
    height: int,
    eye: tuple[float, float, float],
    target: tuple[float, float, float],
    up: tuple[float, float, float],
    fovy: float | None,
    intrinsics: tuple[float, float, float, float] | None,
    effects: bool = True,
    camera: str | None = None,
) -> np.ndarray:
    """Render ``data`` (already forwarded) from ``eye`` towards ``target``, or from the model's
    camera named ``camera`` (fixed or mounted on a body; eye, target and fovy unused); returns
    (H, W, 3) uint8.

    ``renderers``: the caller's cache of ``mujoco.Renderer`` by frame size (it closes them);
    ``asset``: the model's MJCF file, named when the frame exceeds its offscreen buffer;
    ``effects=False``: no shadows, reflections or skybox (a camera observation: ~5x faster with
    software GL, the scene's geometry and colours unchanged).
    """
    import mujoco

    if fovy is not None and intrinsics is not None:
        raise ValueError("render: give fovy or intrinsics, not both")
    if width > model.vis.global_.offwidth or height > model.vis.global_.offheight:
        raise ValueError(
            f"render: {width}x{height} exceeds the offscreen buffer "
            f"{model.vis.global_.offwidth}x{model.vis.global_.offheight} of {asset}"
        )
    renderer = _renderer(model, renderers, width, height)
    if camera is not None:
        if mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera) < 0:
            have = [model.camera(i).name for i in range(model.ncam)]
            raise ValueError(f"camera {camera!r} is not a camera of {asset} (its cameras: {have})")
        renderer.update_scene(data, camera=camera)
        _no_effects(renderer, effects)
        return renderer.render()
    eye_a, target_a = np.asarray(eye, float), np.asarray(target, float)
    forward = target_a - eye_a
    dist = float(np.linalg.norm(forward))
    if dist < 1e-9:
        raise ValueError("render: eye and target coincide")
    forward /= dist
    up_a = np.asarray(up, float)
    up_a = up_a - forward * float(up_a @ forward)  # orthogonalise
    if np.linalg.norm(up_a) < 1e-9:
        raise ValueError("render: up is parallel to the viewing direction")
    up_a /= np.linalg.norm(up_a)

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = target_a
    cam.distance = dist
    cam.azimuth = math.degrees(math.atan2(forward[1], forward[0]))
    cam.elevation = math.degrees(math.asin(float(np.clip(forward[2], -1, 1))))
    renderer.update_scene(data, camera=cam)
    _no_effects(renderer, effects)
    # Place the GL cameras exactly (the free camera has no roll) and set the projection.
    near = model.vis.map.znear * model.stat.extent
    for glcam in renderer.scene.camera:
        glcam.pos[:] = eye_a
        glcam.forward[:] = forward
        glcam.up[:] = up_a
        glcam.frustum_near = near
        glcam.frustum_far = model.vis.map.zfar * model.stat.extent
        if intrinsics is not None:
            fx, fy, cx, cy = (float(v) for v in intrinsics)
            left, right = -near * cx / fx, near * (width - cx) / fx
            glcam.frustum_top = near * cy / fy
            glcam.frustum_bottom = -near * (height - cy) / fy
            glcam.frustum_center = 0.5 * (left + right)
            glcam.frustum_width = 0.5 * (right - left)
        else:
            half = math.radians(fovy if fovy is not None else model.vis.global_.fovy) / 2
            glcam.frustum_top = near * math.tan(half)
            glcam.frustum_bottom = -glcam.frustum_top
            glcam.frustum_center = 0.0
            glcam.frustum_width = glcam.frustum_top * width / height
    return renderer.render()


def _no_effects(renderer: mujoco.Renderer, effects: bool) -> None:
    """``effects=False``: shadows, reflections and skybox off in the renderer's scene."""
    import mujoco

    if not effects:
        for flag in (mujoco.mjtRndFlag.mjRND_SHADOW, mujoco.mjtRndFlag.mjRND_REFLECTION,
                     mujoco.mjtRndFlag.mjRND_SKYBOX):  # fmt: skip
            renderer.scene.flags[flag] = False
