"""SPEC file layouts: trajectory CSV/TUM, tag map YAML/CSV, relocalization CSV.

In memory a trajectory is a DataFrame ``t_ns, x_m, y_m, z_m, qx, qy, qz, qw`` (world_T_cam) and a
tag map is ``tag_id, x_m, y_m, z_m, qx, qy, qz, qw, n_obs[, size_m]`` (world_T_tag). On disk the
layouts are the original ROS 2 tool's (``stamp_sec,stamp_nanosec,x,...``, ``tag36h11:<id>``), and
the readers accept both tagtrail's file names and the original ones (``trajetoria_camera.csv``,
``mapa_tags.csv``). Writers go through a temporary file and ``os.replace``: a crash never leaves
a half-written file.
"""

from __future__ import annotations

import fcntl
import os
import re
import tempfile
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any, cast

import numpy as np
import pandas as pd
import yaml
from numpy.typing import NDArray

from tagtrail import faults
from tagtrail.errors import SourceError, one_line
from tagtrail.schemas.artifacts import EVIDENCE_COLS, POSE_COLS, STD_COLS
from tagtrail.schemas.documents import KnownGround
from tagtrail.schemas.ranges import check_expansion

TRAJ_COLS = ["t_ns", *POSE_COLS]
TAG_COLS = ["tag_id", *POSE_COLS, "n_obs"]
FAMILY = "tag36h11"

TRAJECTORY_NAMES = ("trajectory.csv", "trajetoria_camera.csv")
TAG_MAP_NAMES = ("tag_map.csv", "mapa_tags.csv", "tag_map.yaml")
_CSV_TRAJ_HEADER = ["stamp_sec", "stamp_nanosec", "x", "y", "z", "qx", "qy", "qz", "qw"]
_CSV_TAG_HEADER = ["tag", "x", "y", "z", "qx", "qy", "qz", "qw", "n_obs"]


TEMP_PREFIX = ".tagtrail-tmp-"
"""Every temporary file and folder tagtrail makes starts with this; clean-ups remove only these."""
_TEMP_NAME = re.compile(r"^\.tagtrail-tmp-(.+)\.[A-Za-z0-9_]{8}$")  # mkstemp adds 8 characters


def atomic_write(path: Path, write: Callable[[Path], object]) -> None:
    """Call ``write(tmp)`` on a temporary sibling of ``path``, then rename it into place.

    The sibling is named ``.tagtrail-tmp-<name>.XXXXXXXX`` and holds an ``flock`` while it is
    written, so a clean-up (:func:`remove_stale_temps`) never takes a file another process is
    still writing; the stale ones of earlier writes to ``path`` that were killed are removed."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temps(path.parent, (path.name,))
    fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{path.name}.", dir=path.parent)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)  # released when fd closes, after the rename
        faults.point(f"write:{path.name}")
        write(Path(tmp))
        faults.point(f"written:{path.name}")  # written, not yet in place
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp creates 0600; outputs are ordinary files
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, OSError) and err.filename is None:
            err.filename = str(path)  # a failed write() names no file; say which
        raise
    finally:
        os.close(fd)


def temp_target(name: str) -> str | None:
    """The file a temporary file of :func:`atomic_write` was for, or None if ``name`` is not
    one of tagtrail's temporary names."""
    m = _TEMP_NAME.match(name)
    return m.group(1) if m else None


def remove_stale_temps(folder: Path, names: Collection[str] | None = None) -> list[Path]:
    """Delete the temporary files killed writes left in ``folder`` (for files in ``names`` only,
    when given): only regular files named by :func:`atomic_write` that no process holds (a
    write in progress keeps its ``flock``). Returns what was removed."""
    removed: list[Path] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    for e in entries:
        target = temp_target(e.name)
        if target is None or (names is not None and target not in names):
            continue
        if not e.is_file(follow_symlinks=False):
            continue
        try:
            fd = os.open(e.path, os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.unlink(e.path)
            removed.append(Path(e.path))
        except OSError:
            pass  # being written right now (or already gone)
        finally:
            os.close(fd)
    return removed


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


GROUND_FILE = "ground.json"


def ground_beside(map_path: Path) -> Path:
    """Where a tag map's ``ground.json`` would be: in the map's folder (``optimize`` exports
    both to ``outputs/<dataset>/``)."""
    map_path = Path(map_path)
    return (map_path if map_path.is_dir() else map_path.parent) / GROUND_FILE


def read_ground(path: Path) -> KnownGround:
    """Read a ``ground.json`` (a file, or a folder holding one); bad content is a one-line
    :class:`SourceError` naming the file."""
    f = _resolve(path, (GROUND_FILE,), "ground plane")
    try:
        return KnownGround.model_validate_json(f.read_bytes())
    except (OSError, ValueError) as err:
        raise SourceError(f"{f}: not a ground.json: {one_line(str(err))}") from err


def read_trajectory(path: Path) -> pd.DataFrame:
    """Read a trajectory CSV (tagtrail's or the original tool's) or a TUM file, or a folder.

    Rows must be in time order (equal stamps allowed) with finite values and non-zero
    quaternions; anything else is a :class:`SourceError` naming the file, row and column.
    """
    f = _resolve(path, TRAJECTORY_NAMES, "trajectory")
    if f.suffix not in (".tum", ".txt"):
        return read_stamped_poses(f, _CSV_TRAJ_HEADER, "trajectory")[0]
    return _read_tum(f)


def _read_tum(f: Path) -> pd.DataFrame:
    """``stamp x y z qx qy qz qw`` lines ('#' comments); errors name the line and field."""
    try:
        text = f.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise SourceError(f"{f}: cannot read trajectory: {one_line(err)}") from err
    rows = [(n, line.split("#")[0].split()) for n, line in enumerate(text.splitlines(), 1)]
    lines = [(n, fields) for n, fields in rows if fields]
    names = ["stamp", *_CSV_TRAJ_HEADER[2:]]
    for n, fields in lines:
        if len(fields) != 8:
            raise SourceError(
                f"{f}: line {n}: {len(fields)} fields, a TUM trajectory line has 8 "
                "(stamp x y z qx qy qz qw)"
            )
        for name, cell in zip(names, fields, strict=True):
            try:
                ok = np.isfinite(float(cell))
            except ValueError:
                ok = False
            if not ok:
                raise SourceError(f"{f}: line {n}, field {name}: {cell!r} is not a finite number")
    if not lines:
        return pd.DataFrame(
            {c: pd.Series(dtype=np.int64 if c == "t_ns" else np.float64) for c in TRAJ_COLS}
        )
    arr = np.loadtxt(f, ndmin=2)
    out = pd.DataFrame(arr[:, 1:8], columns=POSE_COLS)
    out.insert(0, "t_ns", np.round(arr[:, 0] * 1e9).astype(np.int64))
    line_of = [n for n, _ in lines]
    _check_quaternions(f, arr[:, 4:8], lambda i: f"line {line_of[i]}")
    _check_order(f, out["t_ns"].to_numpy(), lambda i: f"line {line_of[i]}")
    return out


def read_stamped_poses(
    f: Path, header: list[str], what: str, ordered: bool = True
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """A SPEC CSV of ``stamp_sec, stamp_nanosec, …, x, y, z, qx, qy, qz, qw`` (the last seven
    columns of ``header``) → (``t_ns`` + pose columns, the raw table).

    Every problem is a one-line :class:`SourceError` naming the file, the 1-based data row (the
    header not counted) and the column: a missing column, an empty file, a text or empty cell,
    a non-finite value, a zero quaternion, and (``ordered``) a stamp earlier than the row before.
    """
    df = _read_csv(f, what)
    _require(f, df, header, what)
    sec = _integers(f, df, "stamp_sec", -(2**31), 2**32 - 1)
    nsec = _integers(f, df, "stamp_nanosec", 0, 999_999_999)
    out = pd.DataFrame({"t_ns": sec * 1_000_000_000 + nsec})
    for src, dst in zip(header[-7:], POSE_COLS, strict=True):
        out[dst] = _floats(f, df, src)
    _check_quaternions(f, out[POSE_COLS[3:]].to_numpy(), _data_row)
    if ordered:
        _check_order(f, out["t_ns"].to_numpy(), _data_row)
    return out, df


def read_csv_table(f: Path, what: str, header: list[str]) -> pd.DataFrame:
    """A CSV with at least the columns ``header`` (every problem one :class:`SourceError`)."""
    df = _read_csv(f, what)
    _require(f, df, header, what)
    return df


def integer_column(f: Path, df: pd.DataFrame, col: str, lo: int, hi: int) -> NDArray[np.int64]:
    """Column ``col`` of ``df`` (read from ``f``) as integers in ``[lo, hi]``; else one line
    naming the file, the data row and the column."""
    return _integers(f, df, col, lo, hi)


def _read_csv(f: Path, what: str) -> pd.DataFrame:
    """``pd.read_csv`` with one-line :class:`SourceError` s (an empty file, a ragged row, …)."""
    try:
        return pd.read_csv(f)
    except pd.errors.EmptyDataError as err:
        raise SourceError(f"{f}: empty file (expected a {what} CSV with a header line)") from err
    except (OSError, UnicodeDecodeError, ValueError) as err:  # ParserError is a ValueError
        raise SourceError(f"{f}: cannot read {what} CSV: {one_line(err)}") from err


def _require(f: Path, df: pd.DataFrame, header: list[str], what: str) -> None:
    missing = [c for c in header if c not in df.columns]
    if missing:
        raise SourceError(
            f"{f}: not a{'n' if what[0] in 'aeiou' else ''} {what} CSV, missing columns "
            f"{', '.join(missing)} (header needed: {','.join(header)})"
        )


def _bad_cell(f: Path, row: int, col: str, problem: str) -> SourceError:
    """An error naming ``f``, the 1-based data row (the header is not counted) and the column."""
    return SourceError(f"{f}: {_data_row(row)}, column {col}: {problem}")


def _data_row(i: int) -> str:
    return f"data row {i + 1}"


def _cell_text(value: Any) -> str:  # a cell of any dtype
    return "empty cell" if pd.isna(value) else repr(str(value).strip())


def _floats(f: Path, df: pd.DataFrame, col: str) -> NDArray[np.float64]:
    """Column ``col`` as finite floats; else an error naming the first bad cell."""
    s = df[col]
    numeric = pd.api.types.is_numeric_dtype(s) and not pd.api.types.is_bool_dtype(s)
    v = (s if numeric else pd.to_numeric(s, errors="coerce")).to_numpy(np.float64)
    bad = ~np.isfinite(v)
    if bad.any():
        i = int(np.argmax(bad))
        raw = s.iloc[i]
        if pd.isna(raw):
            problem = "empty cell (or NaN); every cell needs a number"
        elif np.isnan(v[i]) or not numeric:
            problem = f"{_cell_text(raw)} is not a number"
        else:
            problem = f"{_cell_text(raw)} is not finite"
        raise _bad_cell(f, i, col, problem)
    return v


def _integers(f: Path, df: pd.DataFrame, col: str, lo: int, hi: int) -> NDArray[np.int64]:
    """Column ``col`` as integers in ``[lo, hi]``; else an error naming the first bad cell."""
    s = df[col]
    if pd.api.types.is_integer_dtype(s):
        v = s.to_numpy(np.int64)
        bad = (v < lo) | (v > hi)
    else:
        x = _floats(f, df, col)
        bad = (x != np.round(x)) | (x < lo) | (x > hi)
        v = np.where(bad, 0, x).astype(np.int64)
    if bad.any():
        i = int(np.argmax(bad))
        raise _bad_cell(f, i, col, f"{_cell_text(s.iloc[i])} is not an integer in [{lo}, {hi}]")
    return v


def _check_quaternions(f: Path, q: NDArray[np.float64], where: Callable[[int], str]) -> None:
    """Refuse a zero quaternion; ``where(i)`` names row ``i`` (0-based) for the message."""
    zero = np.flatnonzero(np.linalg.norm(q, axis=1) < 1e-9)
    if zero.size:
        i = int(zero[0])
        raise SourceError(
            f"{f}: {where(i)}: quaternion (qx, qy, qz, qw) = {tuple(q[i].tolist())} has zero "
            "length; write the orientation as a unit quaternion"
        )


def _check_order(f: Path, t_ns: NDArray[np.int64], where: Callable[[int], str]) -> None:
    """Refuse a stamp earlier than the one before it (equal stamps are kept)."""
    back = np.flatnonzero(np.diff(t_ns) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise SourceError(
            f"{f}: {where(i)}: stamp {_stamp_text(t_ns[i])} is earlier than the one before "
            f"({_stamp_text(t_ns[i - 1])}); rows must be in time order (sort them by stamp)"
        )


def _stamp_text(t_ns: int) -> str:
    return f"{int(t_ns) // 1_000_000_000}.{int(t_ns) % 1_000_000_000:09d} s"


# --- tag maps ---------------------------------------------------------------------------------


def _opt(x: float) -> str:
    return _fmt(x) if np.isfinite(x) else ""


def tag_map_csv_text(tags: pd.DataFrame) -> str:
    """SPEC's columns, then ``std_pos_m,std_rot_deg`` when the map has them (empty: unknown)."""
    std = all(c in tags.columns for c in STD_COLS)
    lines = [",".join(_CSV_TAG_HEADER + (STD_COLS if std else []))]
    row: Any  # a namedtuple of the columns, their dtypes known at run time only
    for row in tags.itertuples(index=False):
        vals = ",".join(_fmt(getattr(row, c)) for c in POSE_COLS)
        extra = "," + ",".join(_opt(getattr(row, c)) for c in STD_COLS) if std else ""
        lines.append(f"{tag_name(row.tag_id)},{vals},{int(row.n_obs)}{extra}")
    return "\n".join(lines) + "\n"


def trajectory_std_csv_text(traj: pd.DataFrame) -> str:
    """``trajectory_std.csv``: ``stamp_sec,stamp_nanosec,std_pos_m,std_rot_deg,n_tags`` per
    frame (the trajectory CSV's rows; empty cells where the method gives no uncertainty)."""
    t_ns = traj["t_ns"].to_numpy(np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    lines = ["stamp_sec,stamp_nanosec," + ",".join(STD_COLS) + ",n_tags"]
    std = traj[STD_COLS].to_numpy(np.float64)
    n = traj["n_tags"].to_numpy(np.int64)
    for s_, n_, (p, r), k in zip(sec, nsec, std, n, strict=True):
        lines.append(f"{int(s_)},{int(n_)},{_opt(p)},{_opt(r)},{int(k)}")
    return "\n".join(lines) + "\n"


def trajectory_evidence_csv_text(traj: pd.DataFrame) -> str:
    """``trajectory_evidence.csv``: ``stamp_sec,stamp_nanosec,n_tags`` and ``EVIDENCE_COLS`` per
    frame of the trajectory CSV -- its corner RMS, that of the frame on its own corners, and
    how far any temporal step moved it from there (empty cells: unknown)."""
    t_ns = traj["t_ns"].to_numpy(np.int64)
    sec, nsec = np.divmod(t_ns, 1_000_000_000)
    lines = ["stamp_sec,stamp_nanosec,n_tags," + ",".join(EVIDENCE_COLS)]
    vals = traj[EVIDENCE_COLS].to_numpy(np.float64)
    n = traj["n_tags"].to_numpy(np.int64)
    for s_, n_, k, v in zip(sec, nsec, n, vals, strict=True):
        lines.append(f"{int(s_)},{int(n_)},{int(k)}," + ",".join(_opt(x) for x in v))
    return "\n".join(lines) + "\n"


def tag_map_yaml_text(tags: pd.DataFrame, anchor_id: int) -> str:
    entries: dict[str, Any] = {}
    row: Any  # a namedtuple of the columns, their dtypes known at run time only
    for row in tags.itertuples(index=False):
        entry: dict[str, Any] = {
            "position": {"x": float(row.x_m), "y": float(row.y_m), "z": float(row.z_m)},
            "orientation": {
                "x": float(row.qx),
                "y": float(row.qy),
                "z": float(row.qz),
                "w": float(row.qw),
            },
        }
        if "size_m" in tags.columns and pd.notna(row.size_m):
            entry["size"] = float(row.size_m)
        entry["n_obs"] = int(row.n_obs)
        if all(c in tags.columns for c in STD_COLS) and np.isfinite(row.std_pos_m):
            entry["std"] = {
                "position_m": float(row.std_pos_m),
                "orientation_deg": float(row.std_rot_deg),
            }
        entries[tag_name(row.tag_id)] = entry
    doc = {"world_frame": "map", "anchor_tag": tag_name(anchor_id), "tags": entries}
    return yaml.safe_dump(doc, sort_keys=False)


def write_tag_map(folder: Path, tags: pd.DataFrame, anchor_id: int) -> None:
    """Write ``tag_map.yaml`` and ``tag_map.csv`` into ``folder``."""
    atomic_write_text(Path(folder) / "tag_map.yaml", tag_map_yaml_text(tags, anchor_id))
    atomic_write_text(Path(folder) / "tag_map.csv", tag_map_csv_text(tags))


def read_tag_map(path: Path) -> tuple[pd.DataFrame, int | None]:
    """Read a tag map (YAML or CSV, or a folder holding one); returns (tags, anchor id or None).

    For a CSV the anchor is the tag at the identity pose, if any. Bad content (a missing column
    or key, a text cell, a non-finite value, a zero quaternion, a tag listed twice) is a one-line
    :class:`SourceError` naming the file and the row (CSV: 1-based data row) or tag.
    """
    f = _resolve(path, TAG_MAP_NAMES, "tag map")
    if f.suffix in (".yaml", ".yml"):
        return _read_tag_map_yaml(f)
    df = _read_csv(f, "tag map")
    _require(f, df, _CSV_TAG_HEADER[:8], "tag map")
    out = pd.DataFrame({"tag_id": tag_ids(f, df["tag"])})
    for src, dst in zip(_CSV_TAG_HEADER[1:8], POSE_COLS, strict=True):
        out[dst] = _floats(f, df, src)
    out["n_obs"] = _integers(f, df, "n_obs", 0, 2**62) if "n_obs" in df.columns else 0
    _check_quaternions(f, out[POSE_COLS[3:]].to_numpy(), _data_row)
    _check_unique(f, out["tag_id"].to_numpy(), _data_row)
    near_identity = np.isclose(out[POSE_COLS].to_numpy(), [0, 0, 0, 0, 0, 0, 1], atol=1e-12)
    ident = cast("NDArray[np.bool_]", near_identity.all(axis=1))  # one flag per row
    anchor = int(out.loc[ident, "tag_id"].iloc[0]) if ident.any() else None
    return out, anchor


def tag_ids(f: Path, names: pd.Series) -> NDArray[np.int64]:
    """A CSV column of tag names (``tag36h11:<id>``) → ids; errors name the data row."""
    out = np.zeros(len(names), dtype=np.int64)
    for i, name in enumerate(names):
        try:
            out[i] = parse_tag_name("" if pd.isna(name) else name)
        except SourceError:
            raise _bad_cell(
                f,
                i,
                str(names.name),
                f"{_cell_text(name)} is not a tag name (expected 'tag36h11:<id>')",
            ) from None
    return out


def _check_unique(f: Path, ids: NDArray[np.int64], where: Callable[[int], str]) -> None:
    seen: dict[int, int] = {}
    for i, k in enumerate(ids.tolist()):
        if k in seen:
            raise SourceError(
                f"{f}: tag {tag_name(k)} is listed twice ({where(seen[k])} and "
                f"{where(i)}); keep one entry per tag"
            )
        seen[k] = i


def yaml_error_text(err: yaml.YAMLError) -> str:
    """A YAML parse error on one line: ``line L, column C: <problem>``."""
    mark = getattr(err, "problem_mark", None)
    problem = getattr(err, "problem", None) or str(err)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return one_line(f"{where}{problem}")


def load_yaml(f: Path, what: str) -> Any:
    """``yaml.safe_load`` of a file; a one-line :class:`SourceError` if it cannot be parsed."""
    try:
        return check_expansion(yaml.safe_load(Path(f).read_text(encoding="utf-8")))
    except (OSError, UnicodeDecodeError) as err:
        raise SourceError(f"{f}: cannot read {what}: {one_line(err)}") from err
    except yaml.YAMLError as err:
        raise SourceError(f"{f}: not valid YAML ({what}): {yaml_error_text(err)}") from err
    except (ValueError, RecursionError) as err:
        raise SourceError(f"{f}: refused ({what}): {err or 'nested too deeply'}") from err


def _yaml_number(f: Path, where: str, value: Any) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = float("nan")
    if isinstance(value, bool) or not np.isfinite(x):
        raise SourceError(f"{f}: {where} is {value!r}, not a finite number")
    return x


def _read_tag_map_yaml(f: Path) -> tuple[pd.DataFrame, int | None]:
    doc = load_yaml(f, "tag map")
    tags = doc.get("tags") if isinstance(doc, dict) else None
    if not isinstance(tags, dict):
        raise SourceError(
            f"{f}: not a tag map YAML (needs a 'tags:' mapping of 'tag36h11:<id>': "
            "{position: {x, y, z}, orientation: {x, y, z, w}})"
        )
    rows = []
    for name, e in tags.items():
        try:
            tag_id = parse_tag_name(name)
        except SourceError:
            raise SourceError(
                f"{f}: tags: key {name!r} is not a tag name (expected 'tag36h11:<id>')"
            ) from None
        row: dict[str, Any] = {"tag_id": tag_id}
        for key, axes, cols in (
            ("position", "xyz", POSE_COLS[:3]),
            ("orientation", "xyzw", POSE_COLS[3:]),
        ):
            sub = e.get(key) if isinstance(e, dict) else None
            if not isinstance(sub, dict):
                raise SourceError(f"{f}: tag {name}: missing '{key}:' mapping ({', '.join(axes)})")
            for axis, col in zip(axes, cols, strict=True):
                if axis not in sub:
                    raise SourceError(f"{f}: tag {name}: {key}.{axis} is missing")
                row[col] = _yaml_number(f, f"tag {name}: {key}.{axis}", sub[axis])
        n_obs = _yaml_number(f, f"tag {name}: n_obs", e.get("n_obs", 0))
        if n_obs < 0 or n_obs != int(n_obs):
            raise SourceError(f"{f}: tag {name}: n_obs is {e['n_obs']!r}, not a count")
        row["n_obs"] = int(n_obs)
        row["size_m"] = _yaml_number(f, f"tag {name}: size", e["size"]) if "size" in e else np.nan
        rows.append(row)
    names = list(tags)
    out = pd.DataFrame(rows, columns=[*TAG_COLS, "size_m"])
    _check_quaternions(f, out[POSE_COLS[3:]].to_numpy(np.float64), lambda i: f"tag {names[i]}")
    _check_unique(f, out["tag_id"].to_numpy(np.int64), lambda i: f"tag {names[i]}")
    anchor = doc.get("anchor_tag")
    if anchor is None:
        return out, None
    try:
        return out, parse_tag_name(anchor)
    except SourceError:
        raise SourceError(
            f"{f}: anchor_tag {anchor!r} is not a tag name (expected 'tag36h11:<id>')"
        ) from None
