"""`run-cell --config FILE` / `run-cell --dry-run` (the cell itself), `run-cell teach`
(fit the table -> robot frame from jogged points) and `run-cell diagram`."""

from __future__ import annotations

import argparse
import contextlib
import logging
import os
from pathlib import Path
from typing import get_args

from cell.assembly import (
    Overrides,
    RunHooks,
    RunRecipe,
    arm_only,
    assemble,
    attach_consumers,
    cell_config,
    config_path,
    rehearsal_config,
)
from cell.audit import AuditLog
from cell.commands.argtypes import finite_float
from cell.config import CellConfig, load_config
from cell.core.eventbus import EventBus
from cell.core.events import ConfigLoaded, RunEnded
from cell.errors import REPORTED_ERRORS, ConfigError, InputError
from cell.locks import holding
from cell.oplog import log_to_file, stop_logging_to
from cell.planning import save_taught
from cell.recordfile import tell_stderr, unique_stem
from cell.run_config import RunConfig
from cell.runner import EXIT_FAULT, EXIT_STOPPED, Runner
from cell.signals import Controls
from cell.statemachine import markdown, mermaid
from cell.teach import TaughtPoint, check_circles_reachable, check_fit, circle_table_mm, fit_points, jog_session
from drivers.arm.config import ArmKind

log = logging.getLogger(__name__)


def add_run_arguments(parser: argparse.ArgumentParser) -> None:
    """Top-level options: `run-cell` with no sub-command runs the cell."""
    g = parser.add_argument_group("running the cell (no sub-command)")
    g.add_argument(
        "--config", dest="run_config", type=Path, metavar="FILE", help="cell config (TOML); required unless --dry-run"
    )
    g.add_argument(
        "--dry-run",
        action="store_true",
        help="rehearse: a mock arm that records and checks every command and moves nothing; "
        "with no --config, the built-in simulated cell",
    )
    g.add_argument(
        "--arm",
        choices=get_args(ArmKind),
        help="override arm.kind; with the simulated camera, serial|dynamixel drives the real driver "
        "against an emulated arm on a pseudo-terminal (with --dry-run and no --config: "
        "configs/sim-grbl.toml or configs/sim-dynamixel.toml)",
    )
    g.add_argument("--port", help="override arm.port")
    g.add_argument(
        "--recipe",
        dest="run_recipe",
        type=Path,
        metavar="FILE",
        help="run a recipe file: its classes, bins and limits, its taught part types found by their shape models "
        "(with the simulated camera, the table holds sim.taught_parts_per_type of each taught type)",
    )
    g.add_argument(
        "--offset-x-mm",
        type=finite_float,
        default=0.0,
        help="add to planning.offset_x_mm (rehearse a wrong offset: the sim must miss)",
    )
    g.add_argument("--offset-y-mm", type=finite_float, default=0.0, help="add to planning.offset_y_mm")
    g.add_argument("--log-dir", type=Path, help="override run.log_dir")


def register(sub) -> None:
    t = sub.add_parser(
        "teach",
        help="fit the table -> robot transform from points jogged onto plate circles",
        description="Fit the table -> robot transform from plate circles the gripper was jogged onto: the robot "
        "X Y of three or more circles with --point, or jog the arm onto them now with --circles. Writes "
        "planning.taught_path (nothing with --dry-run).",
    )
    t.add_argument("--config", type=Path, help="cell config (TOML); default: built-in")
    t.add_argument(
        "--point",
        nargs=3,
        action="append",
        metavar=("CIRCLE", "X_MM", "Y_MM"),
        default=[],
        help="plate circle number (1 = point 1, row by row) and the robot X Y the gripper was jogged to",
    )
    t.add_argument(
        "--circles",
        nargs="+",
        type=int,
        metavar="CIRCLE",
        help="jog the configured arm onto each of these circles now and record its pose",
    )
    # SUPPRESS: the same options given before `teach` (run-cell's own --arm/--port) still count.
    t.add_argument(
        "--arm", choices=get_args(ArmKind), default=argparse.SUPPRESS, help="override arm.kind (with --circles)"
    )
    t.add_argument("--port", default=argparse.SUPPRESS, help="override arm.port (with --circles)")
    t.add_argument("--dry-run", action="store_true", help="fit and print, write nothing")
    t.set_defaults(func=cmd_teach)

    d = sub.add_parser(
        "diagram",
        help="print the state machine as a Mermaid diagram",
        description="Print the cell's state machine as a Mermaid flowchart (--markdown: docs/state-machine.md).",
    )
    d.add_argument("--markdown", action="store_true", help="the whole docs/state-machine.md")
    d.set_defaults(func=cmd_diagram)


def cmd_diagram(args: argparse.Namespace) -> int:
    print(markdown() if args.markdown else mermaid(), end="")
    return 0


def cmd_teach(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.point and args.circles:
        raise InputError("give either --point (recorded positions) or --circles (jog the arm now), not both")
    if args.circles:
        with arm_only(config, getattr(args, "arm", None), getattr(args, "port", None)) as arm:
            check_circles_reachable(arm, args.circles, config)  # refuse before connecting, let alone moving
            with arm:
                points = jog_session(arm, args.circles, config, input, print)
    else:
        points = []
        for circle, x, y in args.point:
            try:
                n, rx, ry = int(circle), float(x), float(y)
            except ValueError:
                raise InputError(f"--point {circle} {x} {y}: expected a circle number and two numbers") from None
            points.append(TaughtPoint(n, circle_table_mm(n, config), (rx, ry)))
    fit, residuals = fit_points(points, config)
    for p, r in zip(points, residuals, strict=True):
        print(
            f"circle {p.circle:3d}: table ({p.table_mm[0]:7.2f}, {p.table_mm[1]:7.2f}) mm -> "
            f"robot ({p.robot_mm[0]:7.2f}, {p.robot_mm[1]:7.2f}) mm, residual {r:.3f} mm"
        )
    print(
        f"rotation {fit.rotation_deg:+.3f} deg, translation ({fit.tx_mm:.2f}, {fit.ty_mm:.2f}) mm, "
        f"scale {fit.scale:.5f}; largest residual {residuals.max():.3f} mm"
    )
    check_fit(points, residuals, config)
    if args.dry_run:
        print("dry run: nothing written")
        return 0
    with holding(config.planning.taught_path, "taught frame file", wait_s=config.calibration.lock_wait_s):
        save_taught(config.planning.taught_path, fit, [p.to_dict() for p in points], residuals)
    print(f'wrote {config.planning.taught_path}; set planning.frame = "taught" to use it')
    return 0


def overrides_from(args: argparse.Namespace) -> Overrides:
    return Overrides(
        arm=getattr(args, "arm", None),
        port=getattr(args, "port", None),
        log_dir=getattr(args, "log_dir", None),
        offset_x_mm=getattr(args, "offset_x_mm", 0.0) or 0.0,
        offset_y_mm=getattr(args, "offset_y_mm", 0.0) or 0.0,
    )


def run_cell(args: argparse.Namespace) -> int:
    """The job: start-up, the pick loop, the end; stop signals handled in every phase (cell.signals)."""
    if args.run_config is None and not args.dry_run:
        raise ConfigError("give --config FILE to run the cell, or --dry-run to rehearse on the built-in simulated cell")
    args.run_config = config_path(args.run_config, args.dry_run, getattr(args, "arm", None))
    controls = getattr(args, "controls", None) or Controls()
    try:
        config = cell_config(args.run_config, args.dry_run, overrides_from(args))
        recipe = None
        if getattr(args, "run_recipe", None) is not None:
            recipe = RunRecipe.load(args.run_recipe)
            config = recipe.recipe.apply(config)
        if args.dry_run:  # a rehearsal: its own history store, its audit lines marked (never production's)
            config = rehearsal_config(config)
    except REPORTED_ERRORS as e:  # no config to say where logs go: the default (or --log-dir) gets the fault
        with controls.shielded():
            _log_early_fault(args.log_dir or RunConfig().log_dir, args, e)
        raise
    stem = unique_stem(config.run.log_dir, "run", (".jsonl", ".log"))
    audit = _open_audit(Path(f"{stem}.jsonl"), rehearsal=args.dry_run)
    try:
        if not args.verbose:  # the operator's file gets INFO; the terminal keeps to warnings
            for h in logging.getLogger().handlers:
                if type(h) is logging.StreamHandler:
                    h.setLevel(logging.WARNING)
        try:
            log_to_file(f"{stem}.log", exclusive=True)
        except OSError as e:
            raise ConfigError(
                f"run.log_dir {stem.parent}: cannot create the operator log: {e.strerror or e}",
                hint="set run.log_dir (or --log-dir) to a writable folder with free space",
            ) from None
        return _run_job(args, config, audit, controls, recipe)
    finally:
        with controls.shielded():
            audit.close()
            stop_logging_to(f"{stem}.log")


def _run_job(
    args: argparse.Namespace, config: CellConfig, audit: AuditLog, controls: Controls, recipe: RunRecipe | None = None
) -> int:
    resources = contextlib.ExitStack()
    try:
        try:
            audit.record(
                ConfigLoaded(
                    source=str(args.run_config or "built-in"),
                    dry_run=args.dry_run,
                    config=config.model_dump(mode="json"),
                )
            )
            cell = assemble(config, args.dry_run, resources, progress=say, recipe=recipe)
            bus = EventBus()
            resources.callback(bus.close)  # subscribers deliver what they hold before the command ends
            bus.add_record(audit.record, owner=audit)
            attach_consumers(config, bus, resources, RunHooks(controls), rehearsal=args.dry_run)
            for note in cell.notes:
                say(note)
            if recipe is not None and (words := recipe.unbinned_words()):  # said once, before the job
                log.info("%s", words)
                say(words)
            say(
                f"pid {os.getpid()}: Ctrl-C, SIGTERM or SIGHUP stop safely; "
                f"`kill -USR1 {os.getpid()}` pauses and resumes"
            )
        except BaseException as e:
            with controls.shielded():
                audit.best_effort = True
                _log_fault(audit, args, e)
            raise
        with controls.shielded():  # from here the runner decides what a signal interrupts
            sim = cell.sim
            runner = Runner(
                cell.camera,
                cell.arm,
                lambda frame: cell.locate(frame, cell.calibration),
                cell.planner(),
                config.run,
                bus,
                controls,
                cell.expect_motion,
                progress=say,
                truth=None if sim is None else lambda: sim_truth(sim.world),
                sim_motion_s=None if sim is None else cell.motion_time_s,
                drift_watch=cell.drift_watch(cell.calibration),
                calibration_id=lambda: cell.calibration.content_id,
            )
            runner.run()
            return _report(runner, audit, sim)
    finally:
        with controls.shielded():
            resources.close()


def _report(runner: Runner, audit: AuditLog, sim) -> int:
    """The summary on stdout (and on stderr too when the audit log could not keep it); the
    exit code; a last line on stderr naming what failed and where."""
    summary = runner.summary
    lines = summary.lines()
    if sim is not None:
        lines.append(
            "simulated truth: "
            + "; ".join(
                f"{where}: " + ", ".join(f"{n} {kind}" for kind, n in kinds.items())
                for where, kinds in sim_truth(sim.world).items()
            )
        )
    for line in lines:
        say(line)
    say(f"audit log: {audit.path}")
    code = summary.exit_code
    if audit.failed is not None:
        tell_stderr("the audit log is incomplete; the run's summary:\n" + "\n".join(lines))
        code = EXIT_FAULT
    if code == EXIT_FAULT or code == EXIT_STOPPED:
        where = runner.sm.history[-1].source.name if runner.sm.history else "IDLE"
        what = "fault" if code == EXIT_FAULT else "stopped"
        reason = summary.reason if summary.outcome != "done" else f"audit log: {audit.failed}"
        tell_stderr(f"run-cell: {what} in {where}: {reason} (arm made safe; exit {code})")
    return code


def say(line: str) -> None:
    """Print for the operator; a closed terminal (SIGHUP, EIO) must not stop the job or its safe stop."""
    try:
        print(line, flush=True)
    except (OSError, ValueError):
        pass


def _open_audit(path: Path, rehearsal: bool = False) -> AuditLog:
    try:
        return AuditLog(path, rehearsal=rehearsal)
    except OSError as e:
        raise ConfigError(
            f"run.log_dir {path.parent}: cannot create the audit log {path.name}: {e.strerror or e}",
            hint="set run.log_dir (or --log-dir) to a writable folder with free space",
        ) from None


def _log_early_fault(log_dir: Path, args: argparse.Namespace, e: BaseException) -> None:
    """A run whose config failed still leaves a log saying why, where it can (best effort)."""
    try:
        audit = AuditLog(f"{unique_stem(Path(log_dir), 'run', ('.jsonl', '.log'))}.jsonl")
    except OSError as err:
        tell_stderr(f"audit log in {log_dir}: cannot be created ({err.strerror or err})")
        return
    with audit:
        audit.best_effort = True
        _log_fault(audit, args, e)


def _log_fault(audit: AuditLog, args: argparse.Namespace, e: BaseException) -> None:
    """A run that never started still ends its log with the reason."""
    stopped = isinstance(e, KeyboardInterrupt)
    reason = getattr(e, "reason", "Ctrl-C") if stopped else f"{type(e).__name__}: {e}"
    outcome, code = ("stopped", EXIT_STOPPED) if stopped else ("fault", getattr(e, "exit_code", 2))
    if not stopped:
        audit.event("fault", reason=reason, config_file=str(args.run_config or "built-in"))
    audit.record(RunEnded(outcome=outcome, exit_code=code, reason=reason))


def sim_truth(world) -> dict:
    """What actually happened in the simulated world, by place and kind."""
    out: dict[str, dict[str, int]] = {}
    for p in world.parts:
        where = out.setdefault(p.where, {})
        kind = p.spec.name if p.spec.kind == "extruded" else p.spec.kind  # a taught type by its name
        where[kind] = where.get(kind, 0) + 1
    return out
