"""Image-level AprilTag work: detector settings and filters, the detector, corner re-fit."""
