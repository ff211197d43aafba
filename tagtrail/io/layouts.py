"""SPEC file layouts: trajectory CSV/TUM, tag map YAML/CSV, relocalization CSV.

In memory a trajectory is a DataFrame ``t_ns, x_m, y_m, z_m, qx, qy, qz, qw`` (world_T_cam) and a
tag map is ``tag_id, x_m, y_m, z_m, qx, qy, qz, qw, n_obs[, size_m]`` (world_T_tag). On disk the
layouts are the original ROS 2 tool's (``stamp_sec,stamp_nanosec,x,...``, ``tag36h11:<id>``), and
the readers accept both tagtrail's file names and the original ones (``trajetoria_camera.csv``,
``mapa_tags.csv``). Writers go through a temporary file and ``os.replace``: a crash never leaves
a half-written file.
"""

from __future__ import annotations

import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from tagtrail.errors import SourceError

POSE_COLS = ["x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]
TRAJ_COLS = ["t_ns", *POSE_COLS]
TAG_COLS = ["tag_id", *POSE_COLS, "n_obs"]
FAMILY = "tag36h11"

TRAJECTORY_NAMES = ("trajectory.csv", "trajetoria_camera.csv")
TAG_MAP_NAMES = ("tag_map.csv", "mapa_tags.csv", "tag_map.yaml")
_CSV_TRAJ_HEADER = ["stamp_sec", "stamp_nanosec", "x", "y", "z", "qx", "qy", "qz", "qw"]
_CSV_TAG_HEADER = ["tag", "x", "y", "z", "qx", "qy", "qz", "qw", "n_obs"]


def atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(tmp)`` on a temporary sibling of ``path``, then rename it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    os.close(fd)
    try:
        write(Path(tmp))
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def atomic_write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def tag_name(tag_id: int) -> str:
    return f"{FAMILY}:{int(tag_id)}"


def parse_tag_name(name: str | int) -> int:
    """``"tag36h11:7"`` (or ``7``, ``"7"``, ``"tag_7"``) → 7."""
    m = re.search(r"(-?\d+)\s*$", str(name))
    if m is None:
        raise SourceError(f"cannot parse a tag id from {name!r} (expected 'tag36h11:<id>')")
    return int(m.group(1))


# --- trajectories -----------------------------------------------------------------------------


def _fmt(x: float) -> str:
    return repr(float(x))


def trajectory_csv_text(traj: pd.DataFrame) -> str:
    t_ns = traj["t_ns"].to_numpy(np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    lines = [",".join(_CSV_TRAJ_HEADER)]
    vals = traj[POSE_COLS].to_numpy(np.float64)
    for s, n, row in zip(sec, nsec, vals, strict=True):
        lines.append(f"{int(s)},{int(n)}," + ",".join(_fmt(v) for v in row))
    return "\n".join(lines) + "\n"


def write_trajectory_csv(path: Path, traj: pd.DataFrame) -> None:
    atomic_write_text(path, trajectory_csv_text(traj))


def write_trajectory_tum(path: Path, traj: pd.DataFrame) -> None:
    """TUM format (``stamp x y z qx qy qz qw``, space separated, stamp in seconds) for evo."""
    t_ns = traj["t_ns"].to_numpy(np.int64)
    vals = traj[POSE_COLS].to_numpy(np.float64)
    lines = [
        f"{t // 1_000_000_000}.{t % 1_000_000_000:09d} " + " ".join(_fmt(v) for v in row)
        for t, row in zip(t_ns, vals, strict=True)
    ]
    atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


def _resolve(path: Path, names: tuple[str, ...], what: str) -> Path:
    path = Path(path)
    if path.is_dir():
        for name in names:
            if (path / name).is_file():
                return path / name
        raise SourceError(f"{path}: no {what} file found (looked for {', '.join(names)})")
    if not path.is_file():
        raise SourceError(f"{path}: no such file or folder")
    return path


def read_trajectory(path: Path) -> pd.DataFrame:
    """Read a trajectory CSV (tagtrail's or the original tool's) or a TUM file, or a folder."""
    f = _resolve(path, TRAJECTORY_NAMES, "trajectory")
    if f.suffix not in (".tum", ".txt"):
        return read_stamped_poses(f, _CSV_TRAJ_HEADER, "trajectory")[0]
    try:
        arr = np.loadtxt(f, ndmin=2)
    except (OSError, ValueError) as err:
        raise SourceError(f"{f}: cannot read trajectory: {err}") from err
    out = pd.DataFrame(arr[:, 1:8], columns=POSE_COLS)
    out.insert(0, "t_ns", np.round(arr[:, 0] * 1e9).astype(np.int64))
    return out


def read_stamped_poses(
    f: Path, header: list[str], what: str
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A SPEC CSV of ``stamp_sec, stamp_nanosec, …, x, y, z, qx, qy, qz, qw`` (the last seven
    columns of ``header``) → (``t_ns`` + pose columns, the raw table); clear errors."""
    try:
        df = pd.read_csv(f)
    except (OSError, ValueError, pd.errors.ParserError) as err:
        raise SourceError(f"{f}: cannot read {what}: {err}") from err
    missing = [c for c in header if c not in df.columns]
    if missing:
        raise SourceError(f"{f}: not a{'n' if what[0] in 'aeiou' else ''} {what} CSV, "
                          f"missing columns {missing}")
    t_ns = df["stamp_sec"].to_numpy(np.int64) * 1_000_000_000 + df["stamp_nanosec"].to_numpy(
        np.int64
    )
    out = pd.DataFrame({"t_ns": t_ns})
    for src, dst in zip(header[-7:], POSE_COLS, strict=True):
        out[dst] = df[src].to_numpy(np.float64)
    if not np.isfinite(out[POSE_COLS].to_numpy()).all():
        raise SourceError(f"{f}: {what} has non-finite values")
    return out, df


# --- tag maps ---------------------------------------------------------------------------------


def tag_map_csv_text(tags: pd.DataFrame) -> str:
    lines = [",".join(_CSV_TAG_HEADER)]
    for row in tags.itertuples(index=False):
        vals = ",".join(_fmt(getattr(row, c)) for c in POSE_COLS)
        lines.append(f"{tag_name(row.tag_id)},{vals},{int(row.n_obs)}")
    return "\n".join(lines) + "\n"


def tag_map_yaml_text(tags: pd.DataFrame, anchor_id: int) -> str:
    entries: dict[str, Any] = {}
    for row in tags.itertuples(index=False):
        entry: dict[str, Any] = {
            "position": {"x": float(row.x_m), "y": float(row.y_m), "z": float(row.z_m)},
            "orientation": {
                "x": float(row.qx), "y": float(row.qy), "z": float(row.qz), "w": float(row.qw)
            },
        }
        if "size_m" in tags.columns and pd.notna(row.size_m):
            entry["size"] = float(row.size_m)
        entry["n_obs"] = int(row.n_obs)
        entries[tag_name(row.tag_id)] = entry
    doc = {"world_frame": "map", "anchor_tag": tag_name(anchor_id), "tags": entries}
    return yaml.safe_dump(doc, sort_keys=False)


def write_tag_map(folder: Path, tags: pd.DataFrame, anchor_id: int) -> None:
    """Write ``tag_map.yaml`` and ``tag_map.csv`` into ``folder``."""
    atomic_write_text(Path(folder) / "tag_map.yaml", tag_map_yaml_text(tags, anchor_id))
    atomic_write_text(Path(folder) / "tag_map.csv", tag_map_csv_text(tags))


def read_tag_map(path: Path) -> tuple[pd.DataFrame, int | None]:
    """Read a tag map (YAML or CSV, or a folder holding one); returns (tags, anchor id or None).

    For a CSV the anchor is the tag at the identity pose, if any.
    """
    f = _resolve(path, TAG_MAP_NAMES, "tag map")
    try:
        if f.suffix in (".yaml", ".yml"):
            return _read_tag_map_yaml(f)
        df = pd.read_csv(f)
    except (OSError, ValueError, yaml.YAMLError, pd.errors.ParserError) as err:
        raise SourceError(f"{f}: cannot read tag map: {err}") from err
    missing = [c for c in _CSV_TAG_HEADER[:8] if c not in df.columns]
    if missing:
        raise SourceError(f"{f}: not a tag map CSV, missing columns {missing}")
    out = pd.DataFrame({"tag_id": [parse_tag_name(t) for t in df["tag"]]})
    for src, dst in zip(_CSV_TAG_HEADER[1:8], POSE_COLS, strict=True):
        out[dst] = df[src].to_numpy(np.float64)
    out["n_obs"] = df["n_obs"].to_numpy(np.int64) if "n_obs" in df.columns else 0
    ident = np.isclose(out[POSE_COLS].to_numpy(), [0, 0, 0, 0, 0, 0, 1], atol=1e-12).all(axis=1)
    anchor = int(out.loc[ident, "tag_id"].iloc[0]) if ident.any() else None
    return out, anchor


def _read_tag_map_yaml(f: Path) -> tuple[pd.DataFrame, int | None]:
    doc = yaml.safe_load(f.read_text(encoding="utf-8"))
    if not isinstance(doc, dict) or not isinstance(doc.get("tags"), dict):
        raise SourceError(f"{f}: not a tag map YAML (needs a 'tags:' mapping)")
    rows = []
    for name, e in doc["tags"].items():
        try:
            p, q = e["position"], e["orientation"]
            rows.append(
                {
                    "tag_id": parse_tag_name(name),
                    "x_m": float(p["x"]), "y_m": float(p["y"]), "z_m": float(p["z"]),
                    "qx": float(q["x"]), "qy": float(q["y"]), "qz": float(q["z"]),
                    "qw": float(q["w"]),
                    "n_obs": int(e.get("n_obs", 0)),
                    "size_m": float(e["size"]) if "size" in e else np.nan,
                }
            )
        except (KeyError, TypeError, ValueError) as err:
            raise SourceError(f"{f}: tag {name!r} is malformed ({err})") from err
    anchor = doc.get("anchor_tag")
    return pd.DataFrame(rows), (parse_tag_name(anchor) if anchor is not None else None)
