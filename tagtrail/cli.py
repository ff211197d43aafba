"""The ``tagtrail`` command: parse → call → print → exit code (0 ok, 1 failure, 2 user error)."""

from __future__ import annotations

import argparse
import json
import logging
import os
import select
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from tagtrail import faults, signals
from tagtrail.errors import MAX_LINE, TagtrailError, abbreviate, one_line, report, storage_error

if TYPE_CHECKING:
    from tagtrail.runner.execute import Runner
    from tagtrail.stages.base import StageModule

    _SubParsers = argparse._SubParsersAction[argparse.ArgumentParser]  # add_subparsers()'s

EXAMPLES = {
    "run": "examples:\n  tagtrail run\n  tagtrail run optimize -S optimize.f_scale=0.05\n"
    "  tagtrail run --dry-run\n  tagtrail run --force -j 2\n"
    "  tagtrail run --executor dask -j 4   # a local Dask cluster of 4 worker processes\n"
    "  tagtrail run --scheduler tcp://scheduler-host:8786   # an existing Dask cluster",
    "status": "examples:\n  tagtrail status\n  tagtrail status -p my_pipeline.yaml",
    "dag": "examples:\n  tagtrail dag\n  tagtrail dag --mermaid > dag.mmd",
    "show": "examples:\n  tagtrail show extract\n  tagtrail show pnp --dataset query\n"
    "  tagtrail show extract -S extract.quad_decimate=1.0   # the artifact that run made\n"
    "  tagtrail show extract --csv detections.csv\n"
    "  tagtrail show optimize --point 3   # point 3 of the newest `tagtrail sweep`",
}


def _registry() -> dict[str, StageModule]:  # imported lazily so `tagtrail --help` stays fast
    from tagtrail.stages import REGISTRY

    return REGISTRY


def _runner(args: argparse.Namespace, echo: Callable[[str], None] = print) -> Runner:
    from tagtrail.runner.execute import Runner
    from tagtrail.runner.spec import load_pipeline

    pipe = load_pipeline(Path(args.pipeline), _registry(), getattr(args, "set", None) or ())
    scheduler = getattr(args, "scheduler", None)  # `run --executor/--scheduler`
    executor = getattr(args, "executor", None) or ("dask" if scheduler else "local")
    return Runner(
        pipe, jobs=getattr(args, "jobs", 1), echo=echo, executor=executor, scheduler=scheduler
    )


def _stderr(line: str) -> None:
    print(line, file=sys.stderr)


def cmd_run(args: argparse.Namespace) -> int:
    from tagtrail.runner.export import export_outputs

    say = _stderr if args.json else print  # with --json, stdout is the JSON alone
    runner = _runner(args, echo=say)
    if args.dry_run:
        for st in runner.plan(args.stages, force=args.force):
            what = "would run" if st.status == "stale" else "cached"
            print(f"{st.stage + ' [' + st.dataset + ']':<28} {what:<9} ({st.reason})")
        return 0
    from tagtrail.runner.paths import check_project

    check_project(runner.pipe)  # every path the run and its export write, before any work
    t0 = time.perf_counter()
    states = runner.run(args.stages, force=args.force)
    written = export_outputs(runner, force=args.force)
    ran = sum(s.status == "ran" for s in states)
    say(f"{ran} ran, {len(states) - ran} cached in {time.perf_counter() - t0:.2f}s")
    for ds, folder in written.items():
        say(f"outputs [{ds}]: {folder}")
    from tagtrail.commands.answer import answer_text

    answer = answer_text(written, runner.pipe.reference)
    if answer:
        say(answer)
    if args.json:
        from dataclasses import asdict

        print(json.dumps([asdict(s) for s in states], indent=2))
    return 0


def cmd_status(args: argparse.Namespace) -> int:
    runner = _runner(args)
    for st in runner.plan():
        label = "up to date" if st.status == "cached" else "out of date"
        print(
            f"{st.stage + ' [' + st.dataset + ']':<28} {label:<12} "
            + ("" if st.status == "cached" else f"({st.reason})")
        )
    for node, why in sorted(runner.graph.skipped.items()):
        print(f"{str(node):<28} {'n/a':<12} ({why})")
    return 0


def cmd_dag(args: argparse.Namespace) -> int:
    from tagtrail.runner.dag import mermaid, text

    runner = _runner(args)
    print(mermaid(runner.graph) if args.mermaid else text(runner.graph))
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    from tagtrail.runner.show import show

    if args.point is not None:  # a sweep point's overrides, then any -S on top
        from tagtrail.runner.sweep import point_overrides

        name, sets = point_overrides(Path(args.pipeline), args.point, args.sweep)
        print(f"sweep {name}, point {args.point}: {' '.join(sets) or '(no overrides)'}")
        args.set = [*sets, *(args.set or ())]
    elif args.sweep is not None:
        from tagtrail.errors import SpecError

        raise SpecError("--sweep NAME names the sweep of --point N; give --point too")
    return show(_runner(args), args.stage, args.dataset, args.output, args.csv, args.rows)


def _sub(sp: _SubParsers, name: str, help: str) -> argparse.ArgumentParser:
    p = sp.add_parser(
        name,
        help=help,
        description=help,
        epilog=EXAMPLES.get(name),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    return p


def _pipeline_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("-p", "--pipeline", default="pipeline.yaml", help="pipeline file")


def _set_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "-S",
        "--set",
        action="append",
        metavar="STAGE.PARAM=VALUE",
        help="override a stage parameter, as for `run` (repeatable)",
    )


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="tagtrail",
        description="Record a robot's trajectory against AprilTags and relocalize against it.",
        epilog="examples:\n  tagtrail demo\n  tagtrail run\n  tagtrail status\n"
        "  tagtrail show optimize",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sp = parser.add_subparsers(dest="command", metavar="COMMAND")

    p = _sub(sp, "run", "bring the pipeline's stages up to date (make-style)")
    p.add_argument("stages", nargs="*", metavar="STAGE", help="stages to run (with ancestors)")
    _pipeline_arg(p)
    _set_arg(p)
    p.add_argument("--force", action="store_true", help="rerun even if up to date")
    p.add_argument("--dry-run", action="store_true", help="say what would run and why")
    p.add_argument(
        "-j",
        "--jobs",
        type=int,
        default=1,
        help="stages run in parallel (dask: worker processes of the local cluster)",
    )
    p.add_argument(
        "--executor",
        choices=("local", "dask"),
        default=None,
        help="where stages run: local threads (default) or a Dask cluster "
        "(pip install 'tagtrail[dask]')",
    )
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="an existing Dask scheduler (tcp://host:8786; implies --executor dask; "
        "default: start a local cluster)",
    )
    p.add_argument("--json", action="store_true", help="print the run log as JSON")
    p.set_defaults(func=cmd_run)

    p = _sub(sp, "status", "which stages are up to date, and why the others are not")
    _pipeline_arg(p)
    _set_arg(p)
    p.set_defaults(func=cmd_status)

    p = _sub(sp, "dag", "print the stage graph")
    _pipeline_arg(p)
    _set_arg(p)
    p.add_argument("--mermaid", action="store_true", help="mermaid flowchart")
    p.set_defaults(func=cmd_dag)

    p = _sub(sp, "show", "inspect a stage's artifact: schema, rows, head, statistics")
    p.add_argument("stage")
    _pipeline_arg(p)
    _set_arg(p)
    p.add_argument("--dataset", default=None, help="dataset (default: the reference)")
    p.add_argument("--output", default=None, help="which output of the stage")
    p.add_argument("--csv", type=Path, default=None, help="export the table to CSV")
    p.add_argument("--rows", type=int, default=10, help="rows of head to print")
    p.add_argument(
        "--point",
        type=int,
        default=None,
        metavar="N",
        help="the artifact of point N of a `tagtrail sweep` (its -S overrides)",
    )
    p.add_argument(
        "--sweep",
        default=None,
        metavar="NAME",
        help="the sweep of --point (default: the newest under sweeps/)",
    )
    p.set_defaults(func=cmd_show)

    _optional_commands(sp, command)
    return parser


OPTIONAL = (
    ("simulate", "tagtrail.sim.cli", "render rosbag2 recordings with ground truth"),
    ("relocalize", "tagtrail.commands.relocalize", "relocalize a query run against a reference"),
    ("demo", "tagtrail.commands.demo", "simulate the demo recordings and run everything"),
    ("init", "tagtrail.commands.init", "inspect sources and write a pipeline file"),
    ("stream", "tagtrail.stream.cli", "live relocalization over zenoh"),
    ("eval", "tagtrail.commands.eval", "the paper's evaluation tables from a run"),
    ("sweep", "tagtrail.commands.sweep", "run a grid of parameter overrides on the cache"),
    ("export-mcap", "tagtrail.commands.export_mcap", "one run as an MCAP file for Foxglove"),
)


def _optional_commands(sp: _SubParsers, command: str | None) -> None:
    """Commands implemented in their own modules; only the one being run is imported."""
    import importlib

    for name, module, help in OPTIONAL:
        p = _sub(sp, name, help)
        if name == command:
            mod = importlib.import_module(module)
            mod.add_arguments(p)
            p.set_defaults(func=mod.main)


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command)
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(levelname)s %(name)s: %(message)s",
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return run_command(lambda: args.func(args))


def run_command(command: Callable[[], int]) -> int:
    """Run ``command`` and return its exit code; every entry point (``tagtrail …`` and the
    standalone ``python -m`` modules) goes through here. A :class:`TagtrailError` is one
    ``error:`` line and its exit code (2 user error, 1 failure), a refused write (full disk,
    read-only) one line and 2, Ctrl-C 130 and ``interrupted`` (:mod:`tagtrail.signals`), a
    closed stdout pipe (``| head``) nothing and 141, anything else one line plus a traceback
    file, 1."""
    try:
        code = int(command())
        sys.stdout.flush()  # now, not at exit: a reader that has gone is handled below
        return code
    except TagtrailError as err:
        return report(err)
    except BrokenPipeError as err:  # `tagtrail show optimize | head -1`: the reader has gone
        return closed_stdout() if stdout_reader_gone() else _unexpected(err)
    except OSError as err:
        refused = storage_error(err)
        if refused is None:
            return _unexpected(err)
        return report(refused)
    except KeyboardInterrupt as err:  # Ctrl-C, or SIGTERM/SIGHUP under the console script
        return signals.report(err)
    except Exception as err:  # noqa: BLE001 - unexpected: full traceback to a file, one line out
        return _unexpected(err)


SIGPIPE_EXIT = 128 + 13  # 141: what a shell reports for a process a closed pipe ended


def stdout_reader_gone() -> bool:
    """True when stdout is a pipe whose reading end is closed (Linux polls it ``POLLERR``)."""
    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):  # replaced by an in-memory stream (tests)
        return False
    poller = select.poll()
    poller.register(fd, select.POLLOUT)
    return any(events & select.POLLERR for _, events in poller.poll(0))


def closed_stdout() -> int:
    """End quietly after the reader of stdout went away, as Unix tools do: what is still
    buffered goes to /dev/null (the interpreter's last flush would fail again and print
    ``Exception ignored … BrokenPipeError``), and the exit code is SIGPIPE's 141."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, sys.stdout.fileno())
    finally:
        os.close(devnull)
    return SIGPIPE_EXIT


def _unexpected(err: BaseException) -> int:
    """A bug: one line on stderr, the traceback in a file of the system's temp folder."""
    try:
        fd, path = tempfile.mkstemp(prefix="tagtrail-error-", suffix=".log")
        with open(fd, "w") as f:
            f.write("".join(traceback.format_exception(err)))
        where = f" (traceback in {path})"
    except OSError:
        where = ""
    what = abbreviate(one_line(err), MAX_LINE)
    print(f"error: unexpected {type(err).__name__}: {what}{where}", file=sys.stderr)
    return 1


def _kill_dask_workers() -> None:
    executors = sys.modules.get("tagtrail.runner.executors")  # imported only if a run was
    if executors is not None:
        executors.kill_local_workers()


def main_entry() -> None:
    # Stages parallelise across processes and datasets; a multi-threaded BLAS on top of that
    # oversubscribes small machines (measured 2x slower optimize on 2 cores). Set before numpy.
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    from tagtrail import pool

    signals.install()
    signals.at_exit(pool.kill_workers)  # interrupted: the detector workers go with the process
    signals.at_exit(_kill_dask_workers)  # and a local Dask cluster's
    try:
        code = main()
    except KeyboardInterrupt as err:  # outside run_command: parsing arguments, importing
        code = signals.report(err)
    signals.finished()  # a signal from here on ends the process at once, with its line
    faults.point("cli:exit")
    signals.finish(code)


if __name__ == "__main__":
    main_entry()
