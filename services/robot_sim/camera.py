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

In lockstep (:class:`LoopCamera`) robot_sim's loop renders the frame itself, in its own thread: it waits for the
frame's answer anyway, so nothing stalls that would run meanwhile, and the trips to a process and back (the
thread's and the process's wake-ups, the pixels through a pipe, about a millisecond a frame) and the process's
memory go. The same :class:`FrameRenderer` renders the same pixels either way.
"""
from __future__ import annotations

import logging
import os
import pickle
import queue
import signal
import socket
import subprocess
import sys
import threading
from multiprocessing.connection import Connection
from dataclasses import dataclass
from typing import Callable, Optional

import cv2
import mujoco
import numpy as np

from protocol.messages import CHANNELS, CameraInfo, Header, Image, ImageEncoding
from services.model.arm import mujoco_module
from services.paths import REPO
from services.runtime.pacing import normal_priority, request_realtime
from services.runtime.threads import name_os_thread, start_thread
from services.robot_sim import imaging as imaging_mod
from services.robot_sim import scene as scene_mod
from services.robot_sim.imaging import ImagingConfig
from services.robot_sim.sim import Simulation

log = logging.getLogger("mfvs.robot_sim.camera")


#: how long the renderer's process may take to start (a spawned interpreter importing MuJoCo, an EGL context)
RENDERER_START_TIMEOUT_S = 60.0


#: llvmpipe's rasteriser threads for a lockstep frame, per core the renderer may use (more than one core)
LOCKSTEP_RASTERISER_THREADS_PER_CORE = 2
#: the LP_NUM_THREADS that mfvs chose (a value that differs is the user's)
_CHOSEN_BY_MFVS = "MFVS_LP_NUM_THREADS_CHOSEN"


#: the renderer's SCHED_FIFO priority in realtime: above every normal-priority process (vision among them: frames
#: on time, as a camera's own hardware delivers them), below the path of a stop (the router, safety and the e-stop
#: sender at 30). It was the arm's loop's less one (39): at 0.65 of a core a frame took 7 ms, all of it ahead of
#: an e-stop on its way (safety's stop 25-30 ms after the e-stop was sent, against a 20 ms delivery budget). A
#: simulated camera is no reason to hold up a stop; the frame's capture is stamped in the arm's loop, not here.
RENDERER_REALTIME_PRIORITY = 20


def choose_rasteriser_threads(realtime: bool) -> None:
    """How many threads llvmpipe (Mesa's CPU rasteriser) splits a frame across, the one rule for every renderer
    of robot_sim; it sets ``LP_NUM_THREADS`` unless the user did (a GPU driver ignores it). Call before the
    process's first GL context is made (llvmpipe reads the variable as it starts). The same pixels whatever the
    count (llvmpipe renders each tile alone: measured, Table 3's logs and the lockstep identity bench byte for
    byte).

    * realtime: none, the calling thread renders (``0``). On a shared 2-core host its threads at normal priority
      cost a quarter more CPU than one (10.5 against 8.5 ms a 640x480 frame) and waited behind vision and the
      services: frames came late and were dropped. The renderer's own thread, at the camera's priority, renders
      as a camera's own hardware would, on time;
    * lockstep allowed one core (a run pinned beside others: services.experiments.pool): none either, threads there gain
      nothing but their hand-offs;
    * lockstep on more cores: two a core. llvmpipe's default, one a core, split a frame unevenly in a composed
      run on this 2-core machine (0.7 and 1.55 ms of CPU a frame; the caller, submitting and waiting, shares a
      core with one of them): 3.2 ms a frame. Four threads took 0.16-0.94 ms each: 2.3 ms a frame, Table 3's
      p-joint 9.6-10.3 → 8.8-9.1 ms an iteration (interleaved runs). Measured on 2 cores only."""
    current = os.environ.get("LP_NUM_THREADS")
    if current is not None and current != os.environ.get(_CHOSEN_BY_MFVS):
        return  # the user's
    cores = len(os.sched_getaffinity(0))
    threads = str(0 if realtime or cores == 1 else LOCKSTEP_RASTERISER_THREADS_PER_CORE * cores)
    # marked as ours: a child process inherits both and makes its own choice (a realtime renderer started by a
    # process that rendered a lockstep frame must not render with that frame's threads)
    os.environ["LP_NUM_THREADS"] = os.environ[_CHOSEN_BY_MFVS] = threads


class RenderError(RuntimeError):
    """The renderer failed a frame, could not start, or its process is gone."""


class FrameRenderer:
    """A camera's frames from snapshots of the world (the arm's joints and the target; the same at the exposure's
    start, or None; the frame's stamp): its pixels (H×W×3 RGB, or H×W grey as vision's own conversion gives it),
    through the camera's imperfections when it has them. Rendered from a copy of the world of its own, so that
    nothing the simulation does meanwhile changes a frame. Its GL context is made current in the thread that
    renders: render and close it from one thread."""

    def __init__(self, model: mujoco.MjModel, camera_id: int, width: int, height: int,
                 encoding: ImageEncoding = ImageEncoding.RGB8, imaging: Optional[ImagingConfig] = None,
                 camera_matrix: Optional[np.ndarray] = None) -> None:
        self.model, self.camera_id, self.encoding = model, camera_id, encoding
        self.imaging, self.camera_matrix = imaging, camera_matrix
        self.data = mujoco.MjData(model)
        self.renderer = scene_mod.renderer(model, height, width)
        self.pixels = np.empty((height, width, 3), dtype=np.uint8)

    def render(self, qpos: np.ndarray, mocap_pos: np.ndarray, mocap_quat: np.ndarray, start=None,
               stamp_ns: int = 0) -> np.ndarray:
        model, data, camera_id, imaging = self.model, self.data, self.camera_id, self.imaging
        data.qpos[:], data.mocap_pos[:], data.mocap_quat[:] = qpos, mocap_pos, mocap_quat
        mujoco.mj_forward(model, data)
        self.renderer.update_scene(data, camera=camera_id)
        self.renderer.render(out=self.pixels)
        out = cv2.cvtColor(self.pixels, cv2.COLOR_RGB2GRAY) if self.encoding is ImageEncoding.MONO8 else self.pixels
        if imaging is not None:
            if start is not None:
                corners_end = imaging_mod.target_corners_px(model, data, camera_id, self.camera_matrix)
                data.qpos[:], data.mocap_pos[:], data.mocap_quat[:] = start
                mujoco.mj_kinematics(model, data)
                corners_start = imaging_mod.target_corners_px(model, data, camera_id, self.camera_matrix)
                out = imaging_mod.motion_blur(out, corners_end, corners_start, imaging.blur_samples)
            out = imaging_mod.expose(out, imaging, stamp_ns)
        return out

    def close(self) -> None:
        self.renderer.close()


def _serve_frames(conn, model: mujoco.MjModel, camera_id: int, width: int, height: int,
                  realtime_priority: int, encoding: ImageEncoding = ImageEncoding.RGB8,
                  imaging: Optional[ImagingConfig] = None, camera_matrix: Optional[np.ndarray] = None) -> None:
    """The renderer's process: a snapshot in, its frame's pixels out (:class:`FrameRenderer`), until the pipe closes
    or a None comes."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a terminal's Ctrl-C is robot_sim's to handle: it closes us
    name_os_thread("robot_sim-render")
    mujoco_module()  # a spawned interpreter: its MuJoCo warnings to the log too, not to MUJOCO_LOG.TXT
    if realtime_priority > 0:  # without it, llvmpipe's own default (the renderer then shares the cores anyway)
        choose_rasteriser_threads(realtime=True)
    normal_priority()  # the renderer's threads (llvmpipe's) are created now and must not run at realtime priority
    try:
        renderer = FrameRenderer(model, camera_id, width, height, encoding, imaging, camera_matrix)
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
                out = renderer.render(*snapshot)
            except Exception as exc:
                conn.send(f"render failed: {exc}")
                continue
            conn.send_bytes(out.reshape(-1))  # flat: send_bytes counts the first dimension's items
    finally:
        renderer.close()


class RenderProcess:
    """Renders frames of ``model`` from ``camera_id`` in a child process: :meth:`render` blocks (without the
    interpreter lock) until the frame's RGB bytes are back.

    The child is ``python -m services.robot_sim.render_server`` on one end of a socket pair, told what to render
    over it: a plain subprocess, not multiprocessing's spawn, which also starts a resource tracker (a third
    interpreter, 13 MB resident, for shared memory this camera never uses)."""

    def __init__(self, model: mujoco.MjModel, camera_id: int, width: int, height: int,
                 realtime_priority: int = 0, encoding: ImageEncoding = ImageEncoding.RGB8,
                 imaging: Optional[ImagingConfig] = None, camera_matrix: Optional[np.ndarray] = None) -> None:
        self.width, self.height, self.encoding = width, height, encoding
        ours, theirs = socket.socketpair()
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "services.robot_sim.render_server", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),), cwd=REPO)
        finally:
            theirs.close()
        self._conn = Connection(ours.detach())
        try:
            self._conn.send((model, camera_id, width, height, realtime_priority, encoding, imaging, camera_matrix))
        except OSError as exc:
            self.close()
            raise RenderError(f"the renderer's process is gone ({exc})") from exc
        if not self._conn.poll(RENDERER_START_TIMEOUT_S):
            self.close()
            raise RenderError(f"the renderer did not start within {RENDERER_START_TIMEOUT_S:.0f} s")
        try:
            reply = self._conn.recv()
        except (EOFError, OSError) as exc:
            self.close()
            raise RenderError(f"the renderer's process ended as it started ({exc})") from exc
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
        try:
            self._process.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self._process.kill()
            self._process.wait(timeout=5.0)
        self._conn.close()


@dataclass
class Snapshot:
    stamp_ns: int
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    #: the world when the shutter opened (qpos, mocap_pos, mocap_quat), for the motion blur; None without one
    start: Optional[tuple] = None
    #: set once the frame is published (or failed), by the camera's thread
    done: Optional[threading.Event] = None


class _Camera:
    """What both cameras share: the snapshot of the world a frame is rendered from, and the frame published."""

    def __init__(self, sim: Simulation, publish: Callable[[Image], None], header: Callable[..., Header],
                 on_failure: Callable[[], None]) -> None:
        self.sim = sim
        self._publish = publish
        self._header = header
        self._on_failure = on_failure
        #: the last image published (published again when a lockstep answer is late)
        self.last_image: Optional[Image] = None

    def snapshot(self, stamp_ns: int) -> Snapshot:
        """The world now (and at the exposure's start, with a motion blur), for a frame stamped ``stamp_ns``."""
        d = self.sim.data
        imaging = self.sim.scene.camera.imaging
        start = None
        if imaging is not None and imaging.exposure_s > 0:
            start = self.sim.world_at(self.sim.time_ns - int(imaging.exposure_s * 1e9))
        return Snapshot(stamp_ns, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy(), start)

    def _publish_frame(self, snapshot: Snapshot, pixels: bytes) -> None:
        cam = self.sim.scene.camera
        header = self._header("image", stamp_ns=snapshot.stamp_ns, source_stamp_ns=snapshot.stamp_ns)
        image = Image(header=header, width=cam.width, height=cam.height, encoding=cam.encoding, data=pixels)
        self.last_image = image
        self._publish(image)

    def info(self, header: Header) -> CameraInfo:
        return scene_mod.camera_info(self.sim.scene.camera, header)


class SimCamera(_Camera):
    """Renders in a process of its own (:class:`RenderProcess`), fed by a thread of its own: the robot's loop only
    takes the snapshot (:meth:`capture`) and goes on, as a camera's own hardware would let it."""

    def __init__(self, sim: Simulation, publish: Callable[[Image], None], header: Callable[..., Header],
                 on_failure: Callable[[], None], realtime_priority: int = 0) -> None:
        super().__init__(sim, publish, header, on_failure)
        #: the renderer's priority once it exists (0: normal), just below the robot's loop; the renderer's own
        #: threads (llvmpipe's) are created before, at normal priority, and keep it
        self.realtime_priority = realtime_priority
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        self._stopping = threading.Event()
        self._thread: Optional[threading.Thread] = None
        self._renderer: Optional[RenderProcess] = None

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
        """Snapshot the world now for a frame stamped ``stamp_ns``, to be rendered and published by the camera's
        thread: the event it sets then; None when the renderer is still busy with the last one (the frame is
        dropped)."""
        snapshot = self.snapshot(stamp_ns)
        snapshot.done = threading.Event()
        try:
            self._queue.put_nowait(snapshot)
        except queue.Full:
            return None
        return snapshot.done

    def deliver(self, frame: threading.Event, timeout_s: float) -> None:
        """Until the frame :meth:`capture` gave ``frame`` for is published (at most ``timeout_s``)."""
        frame.wait(timeout=timeout_s)

    def _render_loop(self) -> None:
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
                self._publish_frame(snapshot, pixels)
            except Exception:
                self._on_failure()
            finally:
                snapshot.done.set()


class LoopCamera(_Camera):
    """Renders in the thread that delivers the frame: robot_sim's loop in lockstep, which waits for each frame's
    answer anyway. The render process exists for the realtime loop, which must not hold the interpreter lock for
    a frame (module docstring); in lockstep a frame handed to another process and back only cost its trips (about
    a millisecond a frame: the thread's and the process's wake-ups, the pixels through a pipe). The same
    :class:`FrameRenderer` renders the same pixels. Its GL context is the rendering thread's: that thread closes
    it (:meth:`close_renderer`)."""

    def __init__(self, sim: Simulation, publish: Callable[[Image], None], header: Callable[..., Header],
                 on_failure: Callable[[], None]) -> None:
        super().__init__(sim, publish, header, on_failure)
        self._renderer: Optional[FrameRenderer] = None
        self._unavailable = False

    renderer_pid = None

    def start(self) -> None:
        """Nothing to start: the renderer is made by the thread that renders, at its first frame."""

    def capture(self, stamp_ns: int) -> Snapshot:
        """Snapshot the world now for a frame stamped ``stamp_ns`` (rendered when it is delivered)."""
        return self.snapshot(stamp_ns)

    def deliver(self, frame: Snapshot, timeout_s: float) -> None:
        """Render the frame :meth:`capture` took and publish it, in this thread (``timeout_s``: unused, nothing is
        waited for)."""
        try:
            if self._renderer is None:
                if self._unavailable:
                    raise RenderError("no renderer")
                cam = self.sim.scene.camera
                choose_rasteriser_threads(realtime=False)
                try:
                    self._renderer = FrameRenderer(self.sim.model, self.sim.camera_id, cam.width, cam.height,
                                                   cam.encoding, cam.imaging, cam.matrix())
                except Exception as exc:  # no EGL, no display: say why, once
                    self._unavailable = True
                    log.error("camera: no renderer: %s", exc)
                    raise
            pixels = self._renderer.render(frame.qpos, frame.mocap_pos, frame.mocap_quat, frame.start,
                                           frame.stamp_ns)
            self._publish_frame(frame, pixels.tobytes())
        except Exception:
            self._on_failure()

    def close_renderer(self) -> None:
        """Free the renderer; from the thread that rendered (its GL context is current there)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def stop(self) -> None:
        if self._renderer is not None:  # the rendering thread did not close it: it is gone, and so is its context
            log.warning("camera: the renderer was left open by its thread")
