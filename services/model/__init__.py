"""The model of the world the services share: the arm descriptions (:mod:`~services.model.arm`, one file per arm
in ``arms/``, one URDF for MuJoCo and Pinocchio), their kinematics (Pinocchio), frame and rotation math including the
mixed frame (:mod:`~services.model.frames`), and the AprilTag target's geometry (:mod:`~services.model.tag`). Pure:
no zenoh, no threads."""
