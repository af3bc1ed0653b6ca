"""robot_sim's eye-in-hand camera: a frame is a snapshot of the simulated world taken at a cycle boundary (the
arm's joints and the target), rendered in the camera's own thread (the EGL context belongs to it) from its own
copy of the world, and published with the snapshot's time as its capture stamp.

Taking the snapshot costs the robot's loop a few copies; rendering (several ms) never holds it up, and nothing
the loop does later can change a frame being rendered.
"""
from __future__ import annotations

import logging
import os
import queue
import threading
from dataclasses import dataclass
from typing import Callable, Optional

import mujoco
import numpy as np

from protocol.messages import CameraInfo, Header, Image, ImageEncoding
from services.robot.pacing import request_realtime
from services.robot_sim import scene as scene_mod
from services.robot_sim.sim import Simulation

log = logging.getLogger("mfvs.robot_sim.camera")


def normal_priority() -> None:
    """The calling thread back to normal scheduling (a thread of a realtime process inherits its priority)."""
    try:
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass


@dataclass
class Snapshot:
    stamp_ns: int
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    done: threading.Event


class SimCamera:
    def __init__(self, sim: Simulation, publish: Callable[[Image], None], header: Callable[..., Header],
                 on_failure: Callable[[], None], realtime_priority: int = 0) -> None:
        self.sim = sim
        #: the render thread's priority once its renderer exists (0: normal): just below the robot's loop, so that
        #: it is not preempted while it holds the interpreter lock the loop needs; the renderer's own threads
        #: (llvmpipe's) are created before, at normal priority, and keep it
        self.realtime_priority = realtime_priority
        self._publish = publish
        self._header = header
        self._on_failure = on_failure
        self._queue: queue.Queue = queue.Queue(maxsize=1)
        self._stopping = threading.Event()
        self._thread: Optional[threading.Thread] = None
        #: the last image published (published again when a lockstep answer is late)
        self.last_image: Optional[Image] = None

    def start(self) -> None:
        """Start the render thread, and wait until its renderer exists: creating an EGL context holds the
        interpreter lock for a long while, which must happen before the arm's loop runs, not during it."""
        self._ready = threading.Event()
        self._stopping.clear()
        self._thread = threading.Thread(target=self._render_loop, name="robot_sim-render", daemon=True)
        self._thread.start()
        self._ready.wait(timeout=30.0)

    def stop(self) -> None:
        # the loop must end before the process does: a thread still inside EGL while the interpreter tears down
        # crashes it (a full queue once kept the stop sentinel out, and the join gave up)
        self._stopping.set()
        try:
            self._queue.put_nowait(None)
        except queue.Full:
            pass
        if self._thread is not None:
            self._thread.join(timeout=30.0)
            if self._thread.is_alive():
                log.error("camera render thread did not stop within 30 s")

    def capture(self, stamp_ns: int) -> Optional[threading.Event]:
        """Snapshot the world now for a frame stamped ``stamp_ns``; None when the renderer is still busy with the
        last one (the frame is dropped)."""
        d = self.sim.data
        done = threading.Event()
        snapshot = Snapshot(stamp_ns, d.qpos.copy(), d.mocap_pos.copy(), d.mocap_quat.copy(), done)
        try:
            self._queue.put_nowait(snapshot)
        except queue.Full:
            return None
        return done

    def _render_loop(self) -> None:
        normal_priority()  # the renderer's threads are created now and must not run at realtime priority
        model = self.sim.model
        cam = self.sim.scene.camera
        data = mujoco.MjData(model)
        renderer = None
        try:
            try:
                renderer = mujoco.Renderer(model, cam.height, cam.width)
            except Exception:
                self._on_failure()
            finally:
                self._ready.set()
            request_realtime(self.realtime_priority, "camera render thread")
            while not self._stopping.is_set():
                try:
                    snapshot = self._queue.get(timeout=0.1)
                except queue.Empty:
                    continue
                if snapshot is None:
                    return
                try:
                    if renderer is None:
                        raise RuntimeError("no renderer (EGL)")
                    data.qpos[:] = snapshot.qpos
                    data.mocap_pos[:] = snapshot.mocap_pos
                    data.mocap_quat[:] = snapshot.mocap_quat
                    mujoco.mj_forward(model, data)
                    renderer.update_scene(data, camera=self.sim.camera_id)
                    pixels = renderer.render()
                    header = self._header("image", stamp_ns=snapshot.stamp_ns, source_stamp_ns=snapshot.stamp_ns)
                    image = Image(header=header, width=cam.width, height=cam.height, encoding=ImageEncoding.RGB8,
                                  data=pixels.tobytes())
                    self.last_image = image
                    self._publish(image)
                except Exception:
                    self._on_failure()
                finally:
                    snapshot.done.set()
        finally:
            if renderer is not None:
                renderer.close()

    def info(self, header: Header) -> CameraInfo:
        return scene_mod.camera_info(self.sim.scene.camera, header)
