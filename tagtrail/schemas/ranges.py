"""Ranges shared by parameters: every number a parameter takes has a finite range, checked when
the pipeline loads (a value outside is one ``error:`` line, not a crash deep in a stage)."""

from __future__ import annotations

from typing import Annotated

from pydantic import Field

MAX_TAG_ID = 2**31 - 1  # apriltag_msgs' int32 id
TagId = Annotated[int, Field(ge=0, le=MAX_TAG_ID)]
"""A tag id (any family: tag36h11 has 587, tagStandard52h13 48,714)."""
TagSize = Annotated[float, Field(ge=1e-3, le=10.0)]
"""A tag's edge length (black square), m: 1 mm to 10 m."""
Coordinate = Annotated[float, Field(ge=-1e6, le=1e6)]
"""A position coordinate, m (1,000 km either way)."""
QuatComponent = Annotated[float, Field(ge=-10.0, le=10.0)]
"""A quaternion component (normalised after; a zero quaternion is refused where it is read)."""
Scale = Annotated[float, Field(gt=0.0, le=1000.0)]
"""A scale factor."""

MAX_VALUES = 1_000_000  # values a YAML document may hold once its aliases are expanded
MAX_DEPTH = 64  # nesting levels


def check_expansion(doc: object) -> object:
    """``doc`` (a decoded YAML document) if it is of sane size; else ``ValueError``.

    YAML aliases let a file of a few hundred bytes stand for 10^9 values ("billion laughs": a
    list of nine aliases of a list of nine aliases of …): PyYAML builds it cheaply, shared, but
    anything that walks it (validation, an error message printing the value) never ends. Counted
    here in time linear in the *distinct* nodes (each shared node's size remembered); a
    recursive alias (``&a [*a]``) is refused by the depth limit."""
    sizes: dict[int, int] = {}

    def size(node: object, depth: int) -> int:
        if not isinstance(node, dict | list | tuple):
            return 1
        if depth > MAX_DEPTH:
            raise ValueError(f"values nested more than {MAX_DEPTH} levels deep")
        known = sizes.get(id(node))
        if known is not None:
            return known
        children = [*node.keys(), *node.values()] if isinstance(node, dict) else list(node)
        n = 1
        for child in children:
            n += size(child, depth + 1)
            if n > MAX_VALUES:
                raise ValueError(
                    f"more than {MAX_VALUES:,} values once its aliases are "
                    "expanded (a YAML alias bomb?)"
                )
        sizes[id(node)] = n
        return n

    size(doc, 0)
    return doc
