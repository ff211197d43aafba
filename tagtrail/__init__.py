"""tagtrail: AprilTag trajectory recording and relocalization."""

__version__ = "0.1.0"
