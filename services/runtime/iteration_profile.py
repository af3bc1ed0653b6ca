"""Where a lockstep iteration's wall time goes, measured inside each process of a stack (``mfvs bench lockstep``).

Off unless the environment names a directory (:data:`PROFILE_DIR_ENV`): then :func:`install`, which every service
process calls at start, wraps the functions listed in :data:`TIMED` for that process with a timer, and at exit the
process writes its timers and CPU time to ``<dir>/<process>-<pid>.json``. Off, nothing is wrapped: the code that
runs is the code as written, at no cost. A composed stack's services (:mod:`services.stack.composed`) share the bench's
process: :func:`install_composed` times all of theirs there, :func:`profile_now` reads the profile, and
:func:`uninstall` puts the functions back.

A timer adds each call's wall time to its label, per thread, both inclusive and exclusive of the timed calls it
makes itself (a thread's timed calls nest): the exclusive times of one thread's outermost function and everything
timed inside it add up to that function's time exactly. The robot's loop thread in lockstep does the whole
iteration's work or waits for it; its timers are what :func:`per_iteration` splits, the other processes' say what
filled the waits.

The functions are named as ``module:Qualified.name`` strings, resolved when the profile is installed (so this
module imports none of the services it times).
"""
from __future__ import annotations

import atexit
import functools
import importlib
import json
import os
import resource
import threading
import time
from pathlib import Path
from typing import Callable, Optional

from protocol.keys import PIPELINE_SERVICES

#: the directory profiles are written to; unset: no profile (nothing wrapped)
PROFILE_DIR_ENV = "MFVS_PROFILE_DIR"

#: per process: the functions timed, and the label each one's time goes to
TIMED: dict[str, dict[str, str]] = {
    "robot_sim": {
        "services.robot.node:RobotNode.bus_cycle": "node",
        "services.robot.node:RobotNode.dsp_tick": "node",
        "services.robot_sim.hardware:SimulatedHardware.exchange": "bus",
        "services.robot_sim.sim:Simulation.step_physics": "physics",
        "services.robot_sim.firmware:ActuatorFirmware.apply": "actuators",
        "services.robot_sim.service:RobotSimService._at_boundary": "frame_snapshot",
        "services.robot_sim.service:RobotSimService.frame_at_tick": "frame_wait",
        "services.robot_sim.camera:RenderProcess.render": "render",
        "services.robot_sim.camera:FrameRenderer.render": "render",
        "services.robot.node:RobotNode.publish_state": "state",
        "services.robot.node:RobotNode._wait_for_answer": "answer_wait",
        "services.runtime.service:TypedPublisher.put": "publish",
        "services.runtime.service:decode": "decode",
    },
    "vision": {
        "services.vision.core:VisionCore.process": "detection",
        "services.vision.service:VisionService.process": "vision",
        "services.runtime.service:TypedPublisher.put": "publish",
        "services.runtime.service:decode": "decode",
    },
    "controller": {
        "services.controller.core:ControllerCore.step": "law",
        "services.controller.service:ControllerService._on_features": "controller",
        "services.controller.service:ControllerService._on_state": "controller",
        "services.runtime.service:TypedPublisher.put": "publish",
        "services.runtime.service:decode": "decode",
    },
    "safety": {
        "services.safety.service:SafetyService._on_state": "safety",
        "services.safety.service:SafetyService._on_joint_velocity": "safety",
        "services.safety.service:SafetyService._on_twist": "safety",
        "services.runtime.service:TypedPublisher.put": "publish",
        "services.runtime.service:decode": "decode",
    },
}

#: the robot's loop thread: the iteration's critical path
LOOP_THREAD = "robot_sim-loop"
#: robot_sim's frames: calls of this label that returned a frame's stamp
FRAMES_LABEL = "frame_wait"


class _Timers:
    def __init__(self) -> None:
        self._local = threading.local()
        #: (thread name, label) -> [inclusive ns, exclusive ns, calls, calls that returned something]
        self.totals: dict[tuple[str, str], list[int]] = {}
        self._lock = threading.Lock()

    def record(self, label: str) -> list[int]:
        key = (threading.current_thread().name, label)
        found = self.totals.get(key)
        if found is None:
            with self._lock:
                found = self.totals.setdefault(key, [0, 0, 0, 0])
        return found

    def wrap(self, label: str, function: Callable) -> Callable:
        local, clock = self._local, time.perf_counter_ns

        @functools.wraps(function)
        def timed(*args, **kwargs):
            stack = local.__dict__.setdefault("stack", [])
            inner = [0]  # time of the timed calls this one makes
            stack.append(inner)
            start = clock()
            result = None
            try:
                result = function(*args, **kwargs)
                return result
            finally:
                spent = clock() - start
                stack.pop()
                if stack:
                    stack[-1][0] += spent
                totals = self.record(label)
                totals[0] += spent
                totals[1] += spent - inner[0]
                totals[2] += 1
                totals[3] += result is not None

        timed.__wrapped_by_profile__ = True
        return timed


_timers: Optional[_Timers] = None


def enabled() -> bool:
    return bool(os.environ.get(PROFILE_DIR_ENV))


def _resolve(name: str) -> tuple[object, str, Callable]:
    module_name, _, path = name.partition(":")
    owner = importlib.import_module(module_name)
    *parents, attribute = path.split(".")
    for parent in parents:
        owner = getattr(owner, parent)
    return owner, attribute, getattr(owner, attribute)


#: the services of a composed stack (:mod:`services.stack.composed`), all timed in the one process they share
COMPOSED = ("robot_sim", *PIPELINE_SERVICES)

#: what is wrapped now: (owner, attribute, the function as it was), to put back (:func:`uninstall`)
_wrapped: list[tuple[object, str, Callable]] = []


def _wrap(process: str) -> None:
    for name, label in TIMED.get(process, {}).items():
        owner, attribute, function = _resolve(name)
        if isinstance(owner, type):
            # a method the class inherits is timed on the class that defines it (once for every subclass)
            owner = next(klass for klass in owner.__mro__ if attribute in vars(klass))
            function = vars(owner)[attribute]
        if getattr(function, "__wrapped_by_profile__", False):  # another process's, under the same label
            continue
        setattr(owner, attribute, _timers.wrap(label, function))
        _wrapped.append((owner, attribute, function))


def install(process: str) -> bool:
    """Time ``process``'s functions (:data:`TIMED`) and write the profile at exit, when the environment asks for a
    profile; otherwise do nothing. Whether it is on."""
    global _timers
    directory = os.environ.get(PROFILE_DIR_ENV)
    if not directory or _timers is not None:
        return False
    _timers = _Timers()
    _wrap(process)
    atexit.register(_write, Path(directory), process)
    return True


def install_composed() -> None:
    """Time the functions of every service of a composed stack in this process, where they all run: read the profile
    with :func:`profile_now` when the run is over, then :func:`uninstall`."""
    global _timers
    if _timers is not None:
        raise RuntimeError("a profile is installed in this process already")
    _timers = _Timers()
    for process in COMPOSED:
        _wrap(process)


def uninstall() -> None:
    """Every timed function as it was, and no profile."""
    global _timers
    while _wrapped:
        owner, attribute, function = _wrapped.pop()
        setattr(owner, attribute, function)
    _timers = None


def profile_now(process: str) -> dict:
    """The profile so far: the timers, and the CPU the process (and its children, robot_sim's renderer) spent in
    all."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"process": process, "pid": os.getpid(), "cpu_s": time.process_time(),
            "children_cpu_s": children.ru_utime + children.ru_stime,
            "timers": [{"thread": thread, "label": label, "inclusive_ns": t[0], "exclusive_ns": t[1],
                        "calls": t[2], "returned": t[3]}
                       for (thread, label), t in sorted(_timers.totals.items())]}


def _write(directory: Path, process: str) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    (directory / f"{process}-{os.getpid()}.json").write_text(json.dumps(profile_now(process)))


def read_profiles(directory: Path) -> dict[str, dict]:
    """The profiles written to ``directory``, by process."""
    return {p["process"]: p for p in (json.loads(path.read_text()) for path in sorted(Path(directory).glob("*.json")))}


def exclusive_ms(profile: dict, label: str, thread: Optional[str] = None) -> float:
    """A label's exclusive time (ms) in a process, in one thread or all."""
    return sum(t["exclusive_ns"] for t in profile["timers"]
               if t["label"] == label and (thread is None or t["thread"] == thread)) / 1e6


def calls(profile: dict, label: str, returned: bool = False) -> int:
    return sum(t["returned" if returned else "calls"] for t in profile["timers"] if t["label"] == label)
