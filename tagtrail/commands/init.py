"""``tagtrail init``: inspect the sources, pick their topics, write a pipeline file."""

from __future__ import annotations

import argparse
import os
from pathlib import Path
from typing import Any

import yaml

from tagtrail.errors import SourceError, SpecError
from tagtrail.io.layouts import atomic_write_text
from tagtrail.schemas.pipeline import DatasetConfig, Topics
from tagtrail.schemas.profiles import PROFILES, Profile, describe, get_profile

EXAMPLES = """examples:
  tagtrail init --reference bags/run1 --query bags/parked1 --tag-size 0.16
  tagtrail init --reference photos/ --camera photos/camera.yaml --tag-size 0.127
  tagtrail init --reference run1.bag --tag-size 0.16 --anchor 0 -o lab.yaml
  tagtrail init --reference tag_detections.bag --camera cameras.yaml --survey tagslam.yaml
  tagtrail init --profile limo --reference bags/reference --tag-size 0.16  # the LIMO's topics
  tagtrail init --list-profiles"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.epilog = EXAMPLES
    parser.formatter_class = argparse.RawDescriptionHelpFormatter
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        metavar="SRC",
        help="the reference recording (rosbag2 folder, .bag, image folder); required",
    )
    parser.add_argument(
        "--query",
        type=Path,
        action="append",
        default=[],
        metavar="SRC",
        help="a query recording (repeatable: query, query_2, …)",
    )
    parser.add_argument(
        "--camera",
        type=Path,
        default=None,
        metavar="FILE",
        help="camera_info YAML (image folders, or to override the bag's)",
    )
    parser.add_argument(
        "--tag-size",
        type=float,
        default=None,
        metavar="M",
        help="edge of the tags' black square in metres; required unless "
        "--survey or --profile sim gives it (no source format carries it)",
    )
    parser.add_argument(
        "--anchor",
        type=int,
        default=None,
        metavar="ID",
        help="anchor (world) tag id (default: the most observed tag)",
    )
    parser.add_argument(
        "--survey",
        type=Path,
        default=None,
        metavar="FILE",
        help="known tag poses (tagslam.yaml, a WPILib/PhotonVision layout JSON, "
        "a tag_map.yaml): the map in their world (optimize.survey.file), every "
        "part of the tag graph placed by its known tags "
        "(edges.on_disconnected: keep), and the tag sizes the file gives "
        "(pnp.tag_sizes_from)",
    )
    parser.add_argument(
        "-o",
        "--output",
        type=Path,
        default=Path("pipeline.yaml"),
        help="pipeline file to write (pipeline.yaml)",
    )
    parser.add_argument("--force", action="store_true", help="overwrite an existing file")
    parser.add_argument(
        "--profile",
        choices=list(PROFILES),
        default=None,
        help="fill topics and parameters for a robot or the simulator; they are "
        "written into the file (edit them there; --tag-size overrides)",
    )
    parser.add_argument(
        "--list-profiles",
        action="store_true",
        help="list the profiles and what each sets, then exit",
    )


def inspect(
    source: Path, camera: Path | None, topics_given: dict[str, str] | None = None
) -> tuple[DatasetConfig, str]:
    """Open a source as the pipeline will (with ``topics_given``, e.g. a profile's, else the
    topics found by type); return its dataset entry and a one-line description."""
    from tagtrail.io.sources import BagSource, open_source

    cfg = DatasetConfig(
        source=_typed(source),
        camera=_typed(camera) if camera else None,
        topics=Topics(**(topics_given or {})),
    )
    with open_source(cfg) as src:
        topics: dict[str, Any] = {}
        if isinstance(src, BagSource):  # the one source with topics
            topics["detections" if src.kind == "detections" else "image"] = src.topic
            if src.camera_info_topic:
                topics["camera_info"] = src.camera_info_topic
        if src.kind != "observations" and src.camera() is None:
            raise SourceError(
                f"{source}: no camera calibration found; pass --camera FILE "
                "(a ROS camera_info YAML)"
            )
        desc = src.describe()
    return cfg.model_copy(update={"topics": Topics(**topics)}), desc


def _typed(path: Path) -> Path:
    """``path`` made absolute as typed: symlinks kept (a linked data folder stays named so)."""
    return Path(os.path.abspath(path))


def _rel(path: Path, base: Path) -> str:
    try:
        return os.path.relpath(path, base)
    except ValueError:
        return str(path)


NO_SIZE = (
    "the tags' printed size is not known: pass --tag-size M (edge of the black square, "
    "metres) or tag_sizes in pipeline.yaml"
)


def _stage_params(tag_size: float | None, profile: Profile | None = None) -> dict[str, Any]:
    """The ``stages:`` block (the profile's parameters, ``--tag-size`` over them), validated by
    the stages' own models (a file ``run`` accepts). ``pnp.tag_size`` is written only when the
    user or the profile gives it: pnp's built-in default is never written silently."""
    from pydantic import ValidationError

    from tagtrail.stages import REGISTRY, pnp

    stages = {s: dict(ps) for s, ps in (profile.stages if profile else {}).items()}
    if tag_size is not None:
        try:
            pnp.Params(tag_size=tag_size)
        except ValidationError as err:
            msg = err.errors()[0]["msg"]
            raise SpecError(
                f"--tag-size {tag_size}: {msg} (the edge of the black square, in metres)"
            ) from err
        stages.setdefault("pnp", {})["tag_size"] = tag_size
    for stage, params in stages.items():  # a profile's own values must pass too
        REGISTRY[stage].Params(**params)
    return {"pnp": stages.pop("pnp", {}), **stages}


def _survey_params(survey: Path, base: Path, stages: dict[str, Any]) -> str:
    """Name the known-poses file ``survey`` (relative to ``base``, the pipeline's folder) in
    ``stages``: ``optimize.survey.file``, ``edges.on_disconnected: keep`` (parts of the tag
    graph never seen together are placed by their known tags), and ``pnp.tag_sizes_from`` when
    it gives tag sizes (then no ``pnp.tag_size`` is written beside a default size of the file's
    for every other tag: it would never be used); read as ``run`` will (one-line errors naming
    the file). Returns a one-line description."""
    from pydantic import ValidationError

    from tagtrail.schemas.pipeline import SurveyConfig, TagSizesFile

    def first(err: ValidationError) -> str:
        return str(err.errors()[0]["msg"]).removeprefix("Value error, ")

    path = _typed(survey)  # named as given (a symlinked folder stays one)
    try:
        known = SurveyConfig(file=str(path))
    except ValidationError as err:
        raise SpecError(f"--survey: {first(err)}") from err
    name = _rel(path, base)
    stages.setdefault("optimize", {})["survey"] = {"file": name}
    stages.setdefault("edges", {})["on_disconnected"] = "keep"  # each part placed by its tags
    desc = f"survey: {known.format}, known tags {sorted(known.known)}"
    pnp = stages["pnp"]
    try:
        sizes = TagSizesFile(file=str(path))
    except ValidationError as err:  # the file is read above: it gives no (valid) size
        reason = first(err).removeprefix(f"{path}: ")
        if "tag_size" not in pnp:
            raise SpecError(f"{NO_SIZE} (--survey {survey}: {reason})") from err
        return f"{desc}; tag size {pnp['tag_size']} m for every tag: {reason}"
    pnp["tag_sizes_from"] = name
    if sizes.default is not None:
        unused = pnp.pop("tag_size", None)
        note = "" if unused is None else f" (tag size {unused} not written: the file sizes all)"
        return f"{desc}; tag sizes from it: {sizes.sizes}, {sizes.default} m for the others{note}"
    if "tag_size" not in pnp:
        raise SpecError(f"{NO_SIZE} (--survey {survey} sizes only tags {sorted(sizes.sizes)})")
    return f"{desc}; tag sizes from it: {sizes.sizes}, {pnp['tag_size']} m for the others"


def _needs_size(sources: list[Path]) -> bool:
    """Whether some source has tags to measure (images or corners): only an observations folder
    (camera→tag poses given) needs no tag size."""
    return any(
        not (p.name == "observations.csv" or (p / "observations.csv").is_file()) for p in sources
    )


def main(args: argparse.Namespace) -> int:
    if args.list_profiles:
        print("\n".join(describe(p) for p in PROFILES.values()))
        return 0
    if args.reference is None:
        raise SpecError("tagtrail init needs --reference SRC (the reference recording)")
    out: Path = args.output
    if out.exists() and not args.force:
        raise SpecError(f"{out} exists already; use --force to overwrite it")
    profile = get_profile(args.profile)
    stages = _stage_params(args.tag_size, profile)
    base = out.resolve().parent  # run takes relative paths from the file's real folder
    survey = _survey_params(args.survey, base, stages) if args.survey is not None else None
    if not stages["pnp"] and _needs_size([args.reference, *args.query]):
        raise SpecError(NO_SIZE)
    names = ["reference"] + [
        f"query{'' if i == 0 else f'_{i + 1}'}" for i in range(len(args.query))
    ]
    datasets: dict[str, Any] = {}
    for name, src in zip(names, [args.reference, *args.query], strict=True):
        try:
            cfg, desc = inspect(src, args.camera, profile.topics if profile else None)
        except SourceError as err:
            if profile is None:
                raise
            raise SourceError(
                f"{err} (topics of --profile {profile.name}; see tagtrail init --list-profiles)"
            ) from err
        entry: dict[str, Any] = {"source": _rel(cfg.source, base)}
        topics = cfg.topics.model_dump(exclude_none=True)
        if topics:
            entry["topics"] = topics
        if cfg.camera is not None:
            entry["camera"] = _rel(cfg.camera, base)
        datasets[name] = entry
        print(f"{name}: {desc}")
    if survey is not None:
        print(survey)
    if args.anchor is not None:  # the reference's gauge; queries may never see that tag
        datasets["reference"]["params"] = {"edges": {"anchor_id": args.anchor}}
    if not stages["pnp"]:
        del stages["pnp"]
    doc = {"reference": "reference", "datasets": datasets, "stages": stages}
    header = (
        "# Written by `tagtrail init`. Stage parameters not listed keep their defaults;\n"
        "# see `tagtrail dag` and `tagtrail run --dry-run`.\n"
    )
    if profile is not None:
        header += (
            f"# Profile {profile.name}: {profile.description}.\n# Its topics and "
            "parameters are written below as ordinary settings; edit them freely.\n"
        )
    atomic_write_text(out, header + yaml.safe_dump(doc, sort_keys=False))
    print(f"wrote {out}; next: tagtrail run -p {out}")
    return 0
