"""Depth images of the MuJoCo world with the robot in view: what depth cameras beside the table see.

`MujocoRobot.render_depth(cameras, intrinsics)` gives, per camera, the ideal metric depth [H, W] along the
optical axis (0 where nothing is seen) and the robot mask [H, W] (pixels on a robot link: the self-filter a
real system computes from its joint state and its robot model). Noise belongs to the sensor
(`shared.world.sim.camera.StereoDepthNoise`), not to the renderer.

- Cameras: a `CameraPose` (eye, target, world +z up) or a 4x4 T_world_camera in the OpenCV frame (x right,
  y down, z forward), e.g. a camera's true pose under an extrinsic error (`CameraError.true_pose`). The
  OpenGL camera MuJoCo renders with looks along -z with y up; its frustum is set from the intrinsics at
  the near plane, pixel edges at -0.5 and W - 0.5 (H - 0.5) around the principal point, so any pinhole
  with square pixels (fx = fy) renders exactly, whatever its principal point. Measured against MuJoCo's
  own ray casts through the pixel centres (`mj_ray`; tests/test_mujoco_world.py does the same): with
  `Intrinsics.from_hfov` (cx = (W-1)/2, cy = (H-1)/2) and with a principal point 10 px off centre,
  `DepthFrame(depth, intrinsics, T).points_world()` lands within 0.1 mm of the rays' hits on the table,
  the object and the robot, and the object's points on its mesh within 1 mm; a half-pixel shift of the
  convention would put robot pixels ~3 mm off. No other principal point is needed (PyBullet's TinyRenderer
  needs `renderer_intrinsics`, MuJoCo does not).
- Depth: one pass renders depth and segmentation together (MuJoCo's segmentation mode, with which
  `mujoco.Renderer` also renders depth); the reversed-Z depth buffer is turned into metric depth with the
  projection's near / far planes, as `mujoco.Renderer` does. A pixel whose segment is the background
  holds 0.
- Why not `mujoco.Renderer` itself: it needs two passes for depth and segmentation, and it makes its
  OpenGL context current on the calling thread and never releases it, so a second thread (a tracker
  beside the control loop) cannot render with it (EGL_BAD_ACCESS, measured). Here the context is current
  only during a render, from whichever thread asks, one at a time.
- Cost: creating a renderer (OpenGL context, the model's meshes uploaded) takes ~0.15 s, so it is kept
  between calls and rebuilt only for a new model (`reset_world`) or image size; closed on `disconnect`.
  Depth + robot mask of one 424 x 240 camera: 7 ms with the Panda + Allegro, 10 ms with the xArm7 + LEAP,
  a box in view (848 x 480: 23 / 25 ms); Mesa's software OpenGL through EGL on this 2-core machine, no GPU.

Headless rendering needs an OpenGL platform: MuJoCo picks it from `MUJOCO_GL` when it is first imported.
If none works (`MUJOCO_GL` unset on a machine without a display, EGL missing) `RenderUnavailable` says so,
naming `MUJOCO_GL=egl` and the software fallback `MUJOCO_GL=osmesa`.
"""
from __future__ import annotations

import os
import threading
from collections.abc import Sequence

import mujoco
import numpy as np

from shared.execution.robots.mujoco.model import ROBOT_GROUP
from shared.world.perception.depth import Intrinsics
from shared.world.sim.camera import CameraPose


class RenderUnavailable(RuntimeError):
    """MuJoCo cannot render here: no usable OpenGL platform (names what failed and how to choose one)."""


def unavailable(step: str, exc: BaseException) -> RenderUnavailable:
    setting = os.environ.get("MUJOCO_GL")
    return RenderUnavailable(
        f"MuJoCo cannot render depth images: {step} failed ({type(exc).__name__}: {exc}). MuJoCo renders offscreen "
        f"through the OpenGL platform that MUJOCO_GL names when mujoco is first imported (here "
        f"{'unset' if setting is None else repr(setting)}): start the process with MUJOCO_GL=egl (headless: libEGL "
        f"with a GPU driver or Mesa), or MUJOCO_GL=osmesa (software: libOSMesa) where EGL is missing")


def camera_frame(camera: CameraPose | np.ndarray) -> np.ndarray:
    """The OpenCV T_world_camera of a CameraPose, or the 4x4 transform itself."""
    if isinstance(camera, CameraPose):
        return camera.T_world_camera()
    T = np.asarray(camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"a camera is a CameraPose or a finite 4x4 T_world_camera, got shape {T.shape}")
    return T


class DepthRenderer:
    """Depth and robot-mask images of one compiled model at one image size (see the module docstring).
    Not for concurrent use: its owner serialises calls (`MujocoRobot.render_depth`)."""

    def __init__(self, model: mujoco.MjModel, width: int, height: int):
        self.model, self.width, self.height = model, width, height
        # The offscreen framebuffer is allocated with the context from the model's size: grow it if asked for more.
        model.vis.global_.offwidth = max(int(model.vis.global_.offwidth), width)
        model.vis.global_.offheight = max(int(model.vis.global_.offheight), height)
        try:
            gl = mujoco.GLContext(width, height)
        except Exception as exc:  # AttributeError (no platform), ImportError, RuntimeError, EGL errors
            raise unavailable("creating an OpenGL context", exc) from exc
        try:
            with gl.as_current():
                context = mujoco.MjrContext(model, mujoco.mjtFontScale.mjFONTSCALE_100)
                mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, context)
                context.readDepthMap = mujoco.mjtDepthMap.mjDEPTH_ZEROFAR
        except Exception as exc:  # mujoco.FatalError: no OpenGL behind the context
            gl.free()
            raise unavailable("creating MuJoCo's render context", exc) from exc
        self._gl, self._context = gl, context
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 2 * model.ngeom))
        self._scene.flags[mujoco.mjtRndFlag.mjRND_SEGMENT] = True
        self._scene.flags[mujoco.mjtRndFlag.mjRND_IDCOLOR] = True
        self._option = mujoco.MjvOption()
        self._free_camera = mujoco.MjvCamera()
        mujoco.mjv_defaultFreeCamera(model, self._free_camera)
        self._rect = mujoco.MjrRect(0, 0, width, height)
        self._robot_geom = np.append((np.asarray(model.geom_contype) & ROBOT_GROUP) != 0, False)  # [-1]: not a geom
        extent = float(model.stat.extent)
        self.near_m = float(np.float32(model.vis.map.znear * extent))
        self.far_m = float(np.float32(model.vis.map.zfar * extent))

    @property
    def closed(self) -> bool:
        return self._gl is None

    def update_scene(self, data: mujoco.MjData) -> None:
        """Take the bodies' poses from `data` (the caller holds whatever guards it)."""
        mujoco.mjv_updateScene(self.model, data, self._option, None, self._free_camera,
                               mujoco.mjtCatBit.mjCAT_ALL, self._scene)

    def render(self, T_world_camera: np.ndarray, intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
        """(ideal metric depth [H, W], 0 where nothing is seen; robot mask [H, W]) of the scene as last updated."""
        if self._gl is None:
            raise RuntimeError("the depth renderer is closed")
        if (intrinsics.width, intrinsics.height) != (self.width, self.height):
            raise ValueError(f"intrinsics of {intrinsics.width}x{intrinsics.height} px for a "
                             f"{self.width}x{self.height} renderer")
        if not np.isclose(intrinsics.fx, intrinsics.fy, rtol=1e-9):
            raise ValueError(f"MuJoCo renders square pixels: fx {intrinsics.fx} != fy {intrinsics.fy}")
        self._place_camera(T_world_camera, intrinsics)
        rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        buffer = np.empty((self.height, self.width), dtype=np.float32)
        with self._gl.as_current():  # released after: the next render may come from another thread
            mujoco.mjr_render(self._rect, self._scene, self._context)
            mujoco.mjr_readPixels(rgb, buffer, self._rect, self._context)
        rgb, buffer = np.flipud(rgb), np.flipud(buffer)  # OpenGL's first row is the image's last
        segment = rgb[..., 0].astype(np.int64) | (rgb[..., 1].astype(np.int64) << 8) | (rgb[..., 2].astype(np.int64) << 16)
        geom_of_segment = np.full(self._scene.ngeom + 1, -1, dtype=np.int64)  # segment 0 is the background
        for k in range(self._scene.ngeom):
            geom = self._scene.geoms[k]
            if geom.segid >= 0 and geom.objtype == mujoco.mjtObj.mjOBJ_GEOM:
                geom_of_segment[geom.segid + 1] = geom.objid
        geom_at = geom_of_segment[np.clip(segment, 0, len(geom_of_segment) - 1)]
        seen = segment > 0
        depth = np.where(seen, self._metric_depth(buffer), 0.0)
        return depth, self._robot_geom[geom_at] & seen

    def _place_camera(self, T_world_camera: np.ndarray, intrinsics: Intrinsics) -> None:
        T = camera_frame(T_world_camera)
        near, k = self.near_m, intrinsics
        for gl_camera in (self._scene.camera[0], self._scene.camera[1]):  # mono: MuJoCo averages the two eyes
            gl_camera.pos[:] = T[:3, 3]
            gl_camera.forward[:] = T[:3, 2]
            gl_camera.up[:] = -T[:3, 1]
            gl_camera.orthographic = 0
            gl_camera.frustum_near, gl_camera.frustum_far = near, self.far_m
            # Pixel u spans [u - 0.5, u + 0.5] around image point u. With frustum_width 0 MuJoCo sets left /
            # right about the centre from the viewport's aspect, which matches fx for square pixels (a
            # nonzero width is taken as the half width, whatever mjvisualize.h says: measured).
            gl_camera.frustum_center = ((k.width - 1) / 2.0 - k.cx) / k.fx * near
            gl_camera.frustum_top = (k.cy + 0.5) / k.fy * near
            gl_camera.frustum_bottom = -(k.height - 0.5 - k.cy) / k.fy * near
            gl_camera.frustum_width = 0.0

    def _metric_depth(self, buffer: np.ndarray) -> np.ndarray:
        """Reversed-Z depth buffer -> depth along the optical axis (the conversion `mujoco.Renderer` applies)."""
        far, near = np.float32(self.far_m), np.float32(self.near_m)
        c = np.float32(-0.5) * (-(far + near) / (far - near)) - np.float32(0.5)
        d = np.float32(-0.5) * (-(np.float32(2) * far * near) / (far - near))
        metric: np.ndarray = float(d) / (buffer.astype(np.float64) + float(c))
        return metric

    def close(self) -> None:
        """Free the context (from any thread: it is current on none between renders)."""
        if self._gl is None:
            return
        with self._gl.as_current():
            self._context.free()
        self._gl.free()
        self._gl = None


def render_depth(renderer: DepthRenderer, cameras: Sequence[CameraPose | np.ndarray],
                 intrinsics: Intrinsics) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each camera's (depth, robot mask) of the scene `renderer` last took."""
    return [renderer.render(camera_frame(camera), intrinsics) for camera in cameras]


class RendererSlot:
    """The robot's one renderer, kept between calls and rebuilt for another model or image size."""

    def __init__(self) -> None:
        self.lock = threading.Lock()  # one render at a time
        self._renderer: DepthRenderer | None = None

    def get(self, model: mujoco.MjModel, intrinsics: Intrinsics) -> DepthRenderer:
        current = self._renderer
        if current is not None and current.model is model and (current.width, current.height) == (
                intrinsics.width, intrinsics.height):
            return current
        self.close()
        self._renderer = DepthRenderer(model, intrinsics.width, intrinsics.height)
        return self._renderer

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
