"""Images too small to hold a tag never reach the C library, which reads out of bounds on them
(a segfault under ``-S extract.quad_decimate=8`` on a 16 px frame, issue 26 item 11's class)."""

from __future__ import annotations

import subprocess
import sys

SCRIPT = """
import numpy as np
from tagtrail.stages.extract import Params
from tagtrail.vision.apriltag import detect
for side in (1, 2, 3, 4, 8, 12, 16, 17, 24, 32):
    for decimate in (1.0, 2.0, 4.0, 8.0):
        cfg = Params(quad_decimate=decimate).detector()
        ints, floats = detect(np.full((side, side + 3), 255, np.uint8), cfg)
        assert len(ints) == 0 and floats.shape == (0, 9)
print("ok")
"""


def test_tiny_images_give_no_detection_and_no_crash() -> None:
    done = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0 and done.stdout.strip() == "ok", (done.returncode, done.stderr)
