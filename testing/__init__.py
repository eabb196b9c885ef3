"""cellcal.testing: a conformance kit for Camera3D and RobotArm backends."""
