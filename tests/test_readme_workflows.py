"""Every command of the README's two workflow sections, run end to end as written.

The fenced ``sh`` blocks of "Workflow 1: the real robot (LIMO)" and "Workflow 2: simulation"
are taken from README.md and run by bash in a fresh folder, so the README cannot drift from
the code. Only what cannot run here is substituted, in the real-robot section: the robot's
blocks (``# on the robot``) are not run; a zenoh router in this process on 127.0.0.1 stands in
for its bridge (the robot's address becomes it), and the two steps the robot does — drive the
reference path, park at a test pose — become replays of a simulated detections recording
through that router. The simulation section runs verbatim, its loopback ports moved to free
ones. Every session is on 127.0.0.1.
"""

from __future__ import annotations

import csv
import json
import math
import re
from pathlib import Path

import pytest

from tagtrail.sim.simulate import simulate
from tests.readme import run_script, section, shell_blocks
from tests.stream.helpers import free_port, router

pytestmark = pytest.mark.slow  # the README's workflows end to end over zenoh (make test-all)

ROBOT = "tcp/192.168.1.10:7447"


def states(output: str) -> list[dict[str, float]]:
    got = [json.loads(m) for m in re.findall(r"^relocalization/state: (\{.*\})$", output, re.M)]
    assert len(got) == 3, output[-4000:]
    for s in got:
        assert math.isfinite(s["distance_m"]) and math.isfinite(s["heading_error_deg"])
    return got


def metadata_count(bag: Path, topic: str) -> int:
    text = (bag / "metadata.yaml").read_text()
    m = re.search(
        rf"- message_count: (\d+)\n    topic_metadata:\n      name: {re.escape(topic)}\n", text
    )
    assert m, text
    return int(m.group(1))


def check_outputs(project: Path) -> None:
    with open(project / "outputs" / "reference" / "trajectory.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0][:2] == ["stamp_sec", "stamp_nanosec"] and len(rows) > 100
    assert (project / "outputs" / "reference" / "tag_map.yaml").is_file()


def test_real_robot_workflow(tmp_path: Path) -> None:
    robot = simulate("room", tmp_path / "robot", detections=True)
    project = tmp_path / "laptop"
    project.mkdir()
    port = free_port()
    here = f"tcp/127.0.0.1:{port}"
    stand_in = {
        "# drive the robot once along the reference path, then:": (
            f"tagtrail stream replay {robot['reference']} --profile limo --mode client "
            f"--connect {here} --rate 4"
        ),
        "# park the robot at the test pose": (
            f"tagtrail stream replay {robot['query_1']} --profile limo --mode client "
            f"--connect {here} --rate 0.2 &"
        ),
    }
    blocks = shell_blocks(section("Workflow 1: the real robot (LIMO)"))
    assert len(blocks) == 5 and blocks[0].startswith("# on the robot")
    script = "\n".join(blocks[1:])
    for line, command in stand_in.items():
        assert line in script
        script = script.replace(line, command)
    assert ROBOT in script
    bridge = router(port)  # the robot's zenoh-bridge-ros2dds (a router) on loopback
    try:
        out = run_script(script.replace(ROBOT, here), project)
    finally:
        bridge.close()  # type: ignore[no-untyped-call]
    # the robot's detections and camera_info, and its wheel odometry (the profile's optional)
    n = 1828 + metadata_count(robot["reference"], "/odom")
    assert re.search(rf"record: interrupted: {n} messages .* dropped 0", out), out[-4000:]
    assert metadata_count(project / "bags" / "reference", "/detections") == 914
    assert metadata_count(project / "bags" / "reference", "/odom") == n - 1828 > 0
    check_outputs(project)
    d = [s["distance_m"] for s in states(out)]
    assert max(d) - min(d) < 0.05 and max(d) < 2.0  # parked: one pose, near the path


def test_simulation_workflow(tmp_path: Path) -> None:
    ports = {
        "127.0.0.1:7447": f"127.0.0.1:{free_port()}",
        "127.0.0.1:7448": f"127.0.0.1:{free_port()}",
    }
    script = "\n".join(shell_blocks(section("Workflow 2: simulation")))
    for old, new in ports.items():
        assert old in script
        script = script.replace(old, new)
    out = run_script(script, tmp_path)
    assert re.search(r"record: interrupted: 1828 messages .* dropped 0", out), out[-4000:]
    assert (
        metadata_count(tmp_path / "bags" / "reference", "/camera/color/image_raw/compressed") == 914
    )
    check_outputs(tmp_path)
    d = [s["distance_m"] for s in states(out)]
    assert max(d) - min(d) < 0.05 and max(d) < 2.0


if __name__ == "__main__":
    pytest.main([__file__, "-q"])
