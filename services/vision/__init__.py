"""vision: AprilTag corners → normalized point features, depths and the error against the goal."""
