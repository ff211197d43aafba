"""Run tagtrail's CLI with the toy registry: ``python driver.py STAGES_DIR tagtrail-args…``."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from toy import load_registry

import tagtrail.stages
from tagtrail.cli import main

if __name__ == "__main__":
    tagtrail.stages.REGISTRY.clear()
    tagtrail.stages.REGISTRY.update(load_registry(Path(sys.argv[1])))
    sys.exit(main(sys.argv[2:]))
