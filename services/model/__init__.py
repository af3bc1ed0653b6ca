"""The model of the world the services share: the JACO-2 j2s7s300 description (:mod:`~services.model.jaco2`, one
URDF for MuJoCo and Pinocchio), its kinematics (Pinocchio), frame and rotation math including the mixed frame
(:mod:`~services.model.frames`), and the AprilTag target's geometry (:mod:`~services.model.tag`). Pure: no zenoh,
no threads."""
