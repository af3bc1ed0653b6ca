"""robot_sim's eye-in-hand camera: a frame is a snapshot of the simulated world taken at a cycle boundary (the
arm's joints and the target), rendered from its own copy of the world, and published with the snapshot's time as
its capture stamp.

The rendering runs in a process of its own (:class:`RenderProcess`). MuJoCo's Python renderer holds the
interpreter lock for the whole frame (3-5 ms at 640×480 on llvmpipe, measured), and robot_sim's 2 ms loops share
that lock: with the renderer in a thread, every frame stalled the emulated actuators for two cycles, which they
then ran back to back with the host's frames of both lumped into one cycle (the arm took two reference steps in
one cycle, twice the commanded speed, for as long). In a process the renderer has its own lock. The camera's
thread here only hands it a snapshot and waits for the pixels (waiting releases the lock); taking the snapshot
costs the robot's loop a few copies, and nothing the loop does later can change a frame being rendered.
"""
from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import queue
import signal
import threading
from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import mujoco
import numpy as np

from protocol.messages import CHANNELS, CameraInfo, Header, Image, ImageEncoding
from services.model.arm import mujoco_module
from services.robot.pacing import normal_priority, request_realtime
from services.runtime.threads import name_os_thread, start_thread
from services.robot_sim import imaging as imaging_mod
from services.robot_sim import scene as scene_mod
from services.robot_sim.imaging import ImagingConfig
from services.robot_sim.sim import Simulation

log = logging.getLogger("mfvs.robot_sim.camera")

#: how long the renderer's process may take to start (a spawned interpreter importing MuJoCo, an EGL context)
RENDERER_START_TIMEOUT_S = 60.0


class RenderError(RuntimeError):
    """The renderer failed a frame, could not start, or its process is gone."""


def _serve_frames(conn, model: mujoco.MjModel, camera_id: int, width: int, height: int,
                  realtime_priority: int, encoding: ImageEncoding = ImageEncoding.RGB8,
                  imaging: Optional[ImagingConfig] = None, camera_matrix: Optional[np.ndarray] = None) -> None:
    """The renderer's process: a snapshot in (joint positions, target pose; the same at the exposure's start, or
    None; the frame's stamp), its pixels out (RGB, or grey as vision's own conversion gives it), through the
    camera's imperfections when it has them, until the pipe closes or a None comes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is robot_sim's to handle: it closes us
    name_os_thread("robot_sim-render")
    mujoco_module()  # a spawned interpreter: its MuJoCo warnings to the log too, not to MUJOCO_LOG.TXT
    if realtime_priority > 0:
        # llvmpipe (Mesa's CPU rasteriser) splits a frame across a thread per core by default. In realtime, on a
        # shared 2-core host, those threads at normal priority cost a quarter more CPU than one (10.5 against 8.5
        # ms a 640x480 frame) and waited behind vision and the services: frames came late and were dropped. One
        # thread, this one, at the camera's priority renders as a camera's own hardware would, on time. (Lockstep
        # keeps the threads: there the wall time of a frame is what counts. A GPU driver ignores the variable.)
        os.environ.setdefault("LP_NUM_THREADS", "0")
    normal_priority()  # the renderer's threads (llvmpipe's) are created now and must not run at realtime priority
    try:
        data = mujoco.MjData(model)
        renderer = mujoco.Renderer(model, height, width)
        pixels = np.empty((height, width, 3), dtype=np.uint8)
    except Exception as exc:  # no EGL, no display: say why, once
        conn.send(f"no renderer: {exc}")
        return
    request_realtime(realtime_priority, "camera renderer")
    conn.send("ready")
    try:
        while True:
            try:
                snapshot = conn.recv()
            except EOFError:  # robot_sim is gone
                return
            if snapshot is None:
                return
            try:
                qpos, mocap_pos, mocap_quat, start, stamp_ns = snapshot
                data.qpos[:], data.mocap_pos[:], data.mocap_quat[:] = qpos, mocap_pos, mocap_quat
                mujoco.mj_forward(model, data)
                renderer.update_scene(data, camera=camera_id)
                renderer.render(out=pixels)
                out = cv2.cvtColor(pixels, cv2.COLOR_RGB2GRAY) if encoding is ImageEncoding.MONO8 else pixels
                if imaging is not None:
                    if start is not None:
                        corners_end = imaging_mod.target_corners_px(model, data, camera_id, camera_matrix)
                        data.qpos[:], data.mocap_pos[:], data.mocap_quat[:] = start
                        mujoco.mj_kinematics(model, data)
                        corners_start = imaging_mod.target_corners_px(model, data, camera_id, camera_matrix)
                        out = imaging_mod.motion_blur(out, corners_end, corners_start, imaging.blur_samples)
                    out = imaging_mod.expose(out, imaging, stamp_ns)
            except Exception as exc:
                conn.send(f"render failed: {exc}")
                continue
            conn.send_bytes(out.reshape(-1))  # flat: send_bytes counts the first dimension's items
    finally:
        renderer.close()


class RenderProcess:
    """Renders frames of ``model`` from ``camera_id`` in a child process: :meth:`render` blocks (without the
    interpreter lock) until the frame's RGB bytes are back."""

    def __init__(self, model: mujoco.MjModel, camera_id: int, width: int, height: int,
                 realtime_priority: int = 0, encoding: ImageEncoding = ImageEncoding.RGB8,
                 imaging: Optional[ImagingConfig] = None, camera_matrix: Optional[np.ndarray] = None) -> None:
        self.width, self.height, self.encoding = width, height, encoding
        context = multiprocessing.get_context("spawn")  # no fork of a process with threads and realtime loops
        self._conn, child = context.Pipe()
        self._process = context.Process(target=_serve_frames, name="robot_sim-render", daemon=True,
                                        args=(child, model, camera_id, width, height, realtime_priority,
                                              encoding, imaging, camera_matrix))
        self._process.start()
        child.close()
        if not self._conn.poll(RENDERER_START_TIMEOUT_S):
            self.close()
            raise RenderError(f"the renderer did not start within {RENDERER_START_TIMEOUT_S:.0f} s")
        reply = self._conn.recv()
        if reply != "ready":
            self.close()
            raise RenderError(str(reply))

    @property
    def pid(self) -> Optional[int]:
        return self._process.pid

    def render(self, qpos: np.ndarray, mocap_pos: np.ndarray, mocap_quat: np.ndarray, start=None,
               stamp_ns: int = 0) -> bytes:
        """The frame's pixels (H×W×3 RGB or H×W grey, row-major bytes); ``start``: the world at the exposure's
        start (qpos, mocap_pos, mocap_quat) for the motion blur, ``stamp_ns`` the frame's (its noise's seed)."""
        try:
            self._conn.send((qpos, mocap_pos, mocap_quat, start, stamp_ns))
            reply = self._conn.recv_bytes()
        except (EOFError, OSError) as exc:
            raise RenderError(f"the renderer's process is gone ({exc})") from exc
        if len(reply) != self.width * self.height * CHANNELS[self.encoding]:
            raise RenderError(str(pickle.loads(reply)))  # the renderer's reason, sent instead of a frame
        return reply

    def close(self) -> None:
        try:
            self._conn.send(None)
        except (OSError, ValueError):
            pass
        self._process.join(timeout=10.0)
        if self._process.is_alive():
            self._process.kill()
            self._process.join(timeout=5.0)
        self._conn.close()


@dataclass
class Snapshot:
    stamp_ns: int
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    done: threading.Event
    #: the world when the shutter opened (qpos, mocap_pos, mocap_quat), for the motion blur; None without one
    start: Optional[tuple] = None


class SimCamera:
    def __init__(self, sim: Simulation, publish: Callable[[Image], None], header: Callable[..., Header],
                 on_failure: Callable[[], None], realtime_priority: int = 0) -> None:
        self.sim = sim
        #: the renderer's priority once it exists (0: normal), just below the robot's loop; the renderer's own
        #: threads (llvmpipe's) are created before, at normal priority, and keep it
        self.realtime_priority = realtime_priority
        self._publish = publish
        self._header = header
        self._on_failure = on_failure
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        self._stopping = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._renderer: Optional[RenderProcess] = None
        #: the last image published (published again when a lockstep answer is late)
        self.last_image: Optional[Image] = None

    @property
    def renderer_pid(self) -> Optional[int]:
        return self._renderer.pid if self._renderer is not None else None

    def start(self) -> None:
        """Start the renderer's process and wait until it can render, before the arm's loop runs."""
        cam = self.sim.scene.camera
        try:
            self._renderer = RenderProcess(self.sim.model, self.sim.camera_id, cam.width, cam.height,
                                           self.realtime_priority, cam.encoding, cam.imaging, cam.matrix())
        except RenderError as exc:
            log.error("camera: %s", exc)
            self._on_failure()
        self._stopping.clear()
        self._thread = start_thread(self._render_loop, "robot_sim-camera")

    def stop(self) -> None:
        # the loop ends before the process does (a full queue once kept the stop sentinel out, and the join gave up)
        self._stopping.set()
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            if self._thread.is_alive():
                log.error("camera thread did not stop within 30 s")
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def capture(self, stamp_ns: int) -> Optional[threading.Event]:
        """Snapshot the world now for a frame stamped ``stamp_ns``; None when the renderer is still busy with the
        last one (the frame is dropped)."""
        d = self.sim.data
        done = threading.Event()
        imaging = self.sim.scene.camera.imaging
        start = None
        if imaging is not None and imaging.exposure_s > 0:
            start = self.sim.world_at(self.sim.time_ns - int(imaging.exposure_s * 1e9))
        snapshot = Snapshot(stamp_ns, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy(), done, start)
        try:
            self._queue.put_nowait(snapshot)
        except queue.Full:
            return None
        return done

    def _render_loop(self) -> None:
        cam = self.sim.scene.camera
        while not self._stopping.is_set():
            try:
                snapshot = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            if snapshot is None:
                return
            try:
                if self._renderer is None:
                    raise RenderError("no renderer")
                pixels = self._renderer.render(snapshot.qpos, snapshot.mocap_pos, snapshot.mocap_quat,
                                               snapshot.start, snapshot.stamp_ns)
                header = self._header("image", stamp_ns=snapshot.stamp_ns, source_stamp_ns=snapshot.stamp_ns)
                image = Image(header=header, width=cam.width, height=cam.height, encoding=cam.encoding,
                              data=pixels)
                self.last_image = image
                self._publish(image)
            except Exception:
                self._on_failure()
            finally:
                snapshot.done.set()

    def info(self, header: Header) -> CameraInfo:
        return scene_mod.camera_info(self.sim.scene.camera, header)
