"""Opening bags: the one place tagtrail hands a path to rosbags' ``AnyReader``.

A bag is a rosbag2 folder (MCAP or sqlite3; one of its ``.mcap`` / ``.db3`` files names the
folder) or a ROS 1 ``.bag``. Messages are deserialized with tagtrail's typestore
(:func:`tagtrail.io.msgs.typestore`, ``apriltag_msgs`` included).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from tagtrail.errors import SourceError
from tagtrail.io import msgs

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

BAG_FILE_SUFFIXES = (".mcap", ".db3")  # files inside a rosbag2 folder


def bag_path(path: Path) -> Path:
    """The bag ``path`` names: the folder of a rosbag2 storage file, else ``path`` itself."""
    path = Path(path)
    return path.parent if path.suffix in BAG_FILE_SUFFIXES else path


def open_bag(path: Path) -> AnyReader:
    """An open ``AnyReader`` of the bag at ``path`` (:func:`bag_path`); the caller closes it.

    Any failure to open (not a bag, a damaged file, unknown storage) is one
    :class:`SourceError` naming the bag: rosbags raises many types (ReaderError, sqlite3, mcap,
    yaml).
    """
    from rosbags.highlevel import AnyReader

    bag = bag_path(path)
    try:
        reader = AnyReader([bag], default_typestore=msgs.typestore())
        reader.open()
    except Exception as err:
        raise SourceError(f"{bag}: cannot read bag: {err}") from err
    return reader
