"""Named conventions of the wire contract. Every other module refers to these; none redefines them.

A twist declares the frame of its linear part and the meaning of its angular part (docs/contracts.md):

* ``Frame.MIXED`` is Sensors 2022's frame: linear velocity in the robot base frame, rotation of the end effector.
* ``AngularConvention.OMEGA``: the angular velocity vector (in the end-effector frame when the frame is mixed).
* ``AngularConvention.EULER_XYZ_RATES``: true time derivatives of the XYZ Euler angles GetCartesianPosition
  reports, i.e. B(Γ)⁻¹·ω with ω expressed in the base frame.
* ``AngularConvention.SEED000``: what Sensors 2022 eq. 11, 24-25 compute: B(Γ)⁻¹ applied to ω expressed in the
  end-effector frame. It equals EULER_XYZ_RATES only where the end-effector and base frames share the rotation
  axis in question (e.g. at the identity orientation).
"""
from __future__ import annotations

import enum


class Frame(str, enum.Enum):
    BASE = "base"
    END_EFFECTOR = "end_effector"
    CAMERA = "camera"
    MIXED = "mixed"


class AngularConvention(str, enum.Enum):
    OMEGA = "omega"
    EULER_XYZ_RATES = "euler_xyz_rates"
    SEED000 = "seed000"


#: The convention the robot's DSP interprets by default (docs/contracts.md: the seed's controller meets the arm the
#: seed assumes).
DEFAULT_ROBOT_ANGULAR_CONVENTION = AngularConvention.SEED000


#: In lockstep the arm's timeline starts here (ns), so that a stamp of 0 always means "none" (no source image); it
#: advances by exactly one bus cycle per exchange with the host. A host that reaches the emulated arm through a
#: wire that carries no stamps (USB) counts its exchanges from here to stamp what it reads.
LOCKSTEP_EPOCH_NS = 1_000_000_000


class ClockMode(str, enum.Enum):
    """``realtime``: wall clock, robot loops at 100/500 Hz. ``lockstep``: the simulator advances one camera
    period only when the pipeline has answered the last frame (or after a timeout)."""

    REALTIME = "realtime"
    LOCKSTEP = "lockstep"


class ErrorRateSource(str, enum.Enum):
    """Where the PD laws' ė (Sensors 2022 eq. 21: the change of the feature error due to the camera's motion) comes
    from.
    ``camera_motion``: L̂·J_c(q)·q̇, the camera's motion measured by the arm's joint velocities at the frame (no
    differentiation, no filter lag, independent of the frames' spacing). ``frame_difference``: successive errors
    differenced over their image stamps and low-pass filtered (needs no joint velocities)."""

    CAMERA_MOTION = "camera_motion"
    FRAME_DIFFERENCE = "frame_difference"


class DepthSource(str, enum.Enum):
    """Which depth the interaction matrix uses (Sensors 2022; ViSP's CURRENT/DESIRED/MEAN)."""

    CURRENT = "current"
    GOAL = "goal"
    MEAN = "mean"


#: How old an image may be (its capture to now) and still be acted on, along the whole visual path: vision answers
#: an older one with ``stale``, the controller outputs zero for features from it, safety stops a command derived
#: from it. One budget, each service's default (a deployment may tighten one service's). With latency compensation
#: an image's age is no loop delay; 0.15 s turned a loaded host's late frames into stops.
IMAGE_AGE_BUDGET_S = 0.25

#: Euler angles in files and at the Kinova boundary are XYZ: R = Rx(r)·Ry(p)·Rz(y).
EULER_SEQUENCE = "xyz"
