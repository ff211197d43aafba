"""``tagtrail stream`` as a user runs it (issue 10): replay refuses to publish into nothing,
``--wait`` waits, numeric options are validated, bad trajectory files are one ``error:`` line
with exit 2. Real zenoh sessions on 127.0.0.1 only."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import zenoh

from tagtrail.io.layouts import write_trajectory_csv
from tagtrail.stream import cli
from tagtrail.stream.session import make_config
from tests.stream.cases import query_frame
from tests.stream.helpers import free_port, loopback

HEADER = "stamp_sec,stamp_nanosec,x,y,z,qx,qy,qz,qw\n"


def tagtrail(*args: object, cwd: Path, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "tagtrail.cli", *map(str, args)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def one_error_line(stderr: str) -> str:
    """The single ``error:`` line of ``stderr`` (no traceback, nothing else is an error)."""
    errors = [s for s in stderr.splitlines() if "error:" in s]
    assert len(errors) == 1 and "Traceback" not in stderr, stderr
    return errors[0]


@pytest.fixture
def poses(tmp_path: Path) -> Path:
    write_trajectory_csv(tmp_path / "trajectory.csv", query_frame(30, out_of_order=False))
    return tmp_path / "trajectory.csv"


@pytest.fixture
def listener() -> tuple[zenoh.Session, int]:
    """A peer listening on a loopback port, with no subscriber on the replayed key."""
    port = free_port()
    session = zenoh.open(make_config("peer", listen=[loopback(port)]))
    yield session, port
    session.close()


def test_replay_without_subscriber_is_an_error(poses: Path, listener) -> None:
    session, port = listener
    other = session.declare_subscriber("some/other/key", lambda _s: None)
    try:
        t0 = time.monotonic()
        res = tagtrail(
            "stream",
            "replay",
            poses,
            "--connect",
            loopback(port),
            "--wait",
            "1.5",
            cwd=poses.parent,
        )
        dt = time.monotonic() - t0
    finally:
        other.undeclare()
    assert res.returncode == 2, res
    line = one_error_line(res.stderr)
    assert line.startswith("error: ") and "no subscriber on tag_only_pose" in line, line
    assert "--publish-anyway" in line and "published" not in res.stdout
    assert dt >= 1.5, f"--wait 1.5 waited {dt:.2f} s"

    res = tagtrail(
        "stream",
        "replay",
        poses,
        "--connect",
        loopback(port),
        "--wait",
        "0.2",
        "--publish-anyway",
        cwd=poses.parent,
    )
    assert res.returncode == 0, res
    assert "no subscriber on tag_only_pose" in res.stderr and "error:" not in res.stderr
    assert "published 30 messages" in res.stdout


def test_replay_waits_for_a_late_subscriber(poses: Path, listener) -> None:
    """The subscriber appears 1.5 s after replay starts: every pose still reaches it."""
    session, port = listener
    got: list[bytes] = []
    lock = threading.Lock()

    def on_sample(sample: zenoh.Sample) -> None:
        with lock:
            got.append(sample.payload.to_bytes())

    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "tagtrail.cli",
            "stream",
            "replay",
            poses,
            "--rate",
            "0",
            "--connect",
            loopback(port),
            "--wait",
            "20",
        ],
        cwd=poses.parent,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    sub = None
    try:
        time.sleep(1.5)
        assert proc.poll() is None, proc.communicate()
        sub = session.declare_subscriber("tag_only_pose", on_sample)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, err
    assert "published 30 messages" in out
    deadline = time.monotonic() + 10
    while len(got) < 30 and time.monotonic() < deadline:
        time.sleep(0.02)
    if sub is not None:
        sub.undeclare()
    assert len(got) == 30


@pytest.mark.parametrize(
    "args",
    [
        ["replay", "x.csv", "--rate", "-1"],
        ["replay", "x.csv", "--rate", "nan"],
        ["replay", "x.csv", "--rate", "inf"],
        ["replay", "x.csv", "--wait", "-0.5"],
        ["replay", "x.csv", "--count", "-1"],
        ["replay", "x.csv", "--count", "2.5"],
        ["relocalize", "--reference", "r.csv", "--path-period", "-1"],
        ["relocalize", "--reference", "r.csv", "--path-max-points", "-5"],
        ["relocalize", "--reference", "r.csv", "--duration", "1e999"],
        ["relocalize", "--reference", "r.csv", "--stats-period", "-10"],
        ["localize", "--map", "m.yaml", "--tag-size", "0"],
        ["localize", "--map", "m.yaml", "--max-hamming", "-1"],
        ["localize", "--map", "m.yaml", "--min-decision-margin", "nan"],
    ],
)
def test_bad_numbers_are_one_error_line(args: list[str], capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    line = one_error_line(err)
    assert args[-2] in line and repr(args[-1]) in line, line


def test_replay_rate_minus_one_as_a_user(tmp_path: Path, poses: Path) -> None:
    res = tagtrail("stream", "replay", poses, "--rate", "-1", cwd=tmp_path)
    assert res.returncode == 2
    assert "--rate: must be a finite number >= 0, got '-1'" in one_error_line(res.stderr)


@pytest.mark.parametrize(
    ("row", "want"),
    [
        ("2,0,abc,0,0,0,0,0,1\n", "column x"),
        ("2,0,1,0,0,0,0,0,0\n", "quaternion"),
    ],
)
def test_bad_trajectory_csv_is_one_error_line(tmp_path: Path, row: str, want: str) -> None:
    """Needs the shared reader's SourceError naming file, row and column (tagtrail.io.layouts)."""
    bad = tmp_path / "bad.csv"
    bad.write_text(HEADER + "1,0,0,0,0,0,0,0,1\n" + row)
    port = str(free_port())
    for args in (
        ["replay", bad, "--connect", loopback(port), "--wait", "0"],
        ["relocalize", "--reference", bad, "--listen", loopback(port)],
    ):
        res = tagtrail("stream", *args, cwd=tmp_path, timeout=30)
        assert res.returncode == 2, res
        line = one_error_line(res.stderr)
        assert line.startswith("error: ") and "bad.csv" in line and "row 2" in line, line
        assert want in line and "unexpected" not in line, line
        assert res.stdout == ""


def test_replay_of_a_header_only_csv_is_an_error(tmp_path: Path) -> None:
    (tmp_path / "empty.csv").write_text(HEADER)
    res = tagtrail("stream", "replay", tmp_path / "empty.csv", "--wait", "0", cwd=tmp_path)
    assert res.returncode == 2
    assert "empty.csv: no poses to replay" in one_error_line(res.stderr)


GROUND = (
    '{"normal": [0, 1, 0], "offset_m": -0.13, "normal_camera": [0, -1, 0], '
    '"forward_camera": [0, 0, 1], "lever_m": 0.084}'
)


def _map_folder(tmp_path: Path, ground: str | None) -> Path:
    """A tag map folder as ``optimize`` exports it, with ``ground.json`` (or without)."""
    folder = tmp_path / "outputs" / "reference"
    folder.mkdir(parents=True)
    (folder / "tag_map.yaml").write_text(
        "tags:\n  tag36h11:0:\n    position: {x: 0, y: 0, z: 0}\n"
        "    orientation: {x: 0, y: 0, z: 0, w: 1}\n"
    )
    if ground is not None:
        (folder / "ground.json").write_text(ground)
    return folder


@pytest.mark.parametrize(
    ("ground", "flag", "said"),
    [
        (
            GROUND,
            [],
            "held from the first frame (dropped, with a warning, if this run's "
            "camera sits off it); its camera mount too, unless",
        ),
        (
            GROUND.replace(', "forward_camera": [0, 0, 1], "lever_m": 0.084', ""),
            [],
            "camera sits off it)\n",
        ),
        (GROUND, ["--ground", "none"], "--ground none: the ground plane is fitted"),
        (None, [], "no ground.json beside the map"),
        (GROUND, ["--no-smooth", "--ground", "none"], "--ground is for --smooth"),
    ],
)
def test_localize_says_where_its_ground_plane_comes_from(
    tmp_path: Path, ground: str | None, flag: list[str], said: str
) -> None:
    """``--smooth`` holds the ``ground.json`` beside the map (optimize's export) from the first
    frame and says so; ``--ground none`` or no such file: fitted to the run, said too."""
    folder = _map_folder(tmp_path, ground)
    port = free_port()
    res = tagtrail(
        "stream", "localize", "--map", folder, "--smooth", "--camera-forward", "0.084", *flag,
        "--listen", loopback(port), "--duration", "0.5", "--stats-period", "0",
        cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert said in res.stderr, res.stderr


@pytest.mark.parametrize(
    ("ground", "want"),
    [
        ('{"normal": [0, 0, 0], "offset_m": 0, "normal_camera": [0, -1, 0]}', "zero vector"),
        ('{"normal": [0, 1, 0], "normal_camera": [0, -1, 0]}', "offset_m"),
        ("{not json", "not a ground.json"),
    ],
)
def test_a_bad_ground_json_is_one_error_line(tmp_path: Path, ground: str, want: str) -> None:
    folder = _map_folder(tmp_path, ground)
    res = tagtrail(
        "stream", "localize", "--map", folder / "tag_map.yaml", "--smooth",
        "--listen", loopback(free_port()), "--duration", "0.5",
        cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 2, res
    line = one_error_line(res.stderr)
    assert "ground.json" in line and want in line, line


def test_low_latency_is_refused_for_images(tmp_path: Path) -> None:
    """zenoh's low-latency transport does not fragment: a localize node that takes images
    refuses ``--low-latency`` (one error line) instead of losing frames over it."""
    folder = _map_folder(tmp_path, None)
    res = tagtrail(
        "stream", "localize", "--map", folder / "tag_map.yaml", "--image-key", "image",
        "--low-latency", "--listen", loopback(free_port()), "--duration", "0.5",
        cwd=tmp_path,
    )  # fmt: skip
    assert res.returncode == 2, res
    line = one_error_line(res.stderr)
    assert "--low-latency" in line and "image" in line, line
