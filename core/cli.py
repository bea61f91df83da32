"""The ``vistac`` command line.

Exit codes: 0 success, 1 the skill failed or a runtime error, 2 invalid input (skill file,
plugin name, option), 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from vistac import __version__
from vistac.allocator import keep_freed_memory
from vistac.errors import ConfigError, PluginError, VistacError
from vistac.pluginmanager import Plugins, load_plugins

log = logging.getLogger("vistac")


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time of the record (not at setup)."""

    @property
    def stream(self) -> Any:
        return sys.stderr

    @stream.setter
    def stream(self, value: Any) -> None:
        del value


def _setup_logging(quiet: bool, verbose: bool) -> None:
    level = logging.WARNING if quiet else logging.DEBUG if verbose else logging.INFO
    handler = _StderrHandler()
    handler.setFormatter(
        logging.Formatter("%(message)s" if not verbose else "%(name)s: %(message)s")
    )
    root = logging.getLogger("vistac")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


def _plugins(args: argparse.Namespace) -> Plugins:
    plugins = load_plugins(args.plugin)
    missing = [f for f in plugins.failures if f.name in args.plugin]
    if missing:
        raise PluginError("; ".join(f"plugin {f.name}: {f.error}" for f in missing))
    return plugins


def cmd_run(args: argparse.Namespace) -> int:
    from vistac.scheduler import Scheduler
    from vistac.skill import load_skill

    plugins = _plugins(args)
    skill = load_skill(args.skill, plugins.registry, args.set)
    scheduler = Scheduler(skill, plugins, args.out, seed=args.seed, overwrite=args.overwrite)
    result = scheduler.run()
    if result.summary:  # none when it failed before it started
        print(format_summary(result.summary, result.out_dir))
    if result.error:
        print(f"error: {result.error}", file=sys.stderr)
    return result.exit_code


def cmd_replay(args: argparse.Namespace) -> int:
    from vistac.replay import replay

    summary = replay(args.run, args.out, _plugins(args), args.set, args.overwrite)
    print(format_summary(summary, args.out))
    return 0


def format_summary(summary: dict[str, Any], out_dir: Path) -> str:
    """A short human-readable account of a run."""
    lines = [
        f"skill {summary['skill']!r}: {summary['status']} in {summary['wall_time_s']:.1f} s"
        + (f" ({summary['sim_time_s']:.1f} s simulated)" if summary.get("sim_time_s") else "")
    ]
    if summary.get("views"):
        lines.append(f"  looked from {summary['views']} views")
    for episode in summary.get("episodes", []):
        action = episode["action"]
        x, y = action["point_m"]
        text = (
            f"  episode {episode['index']}: {action['kind']} at ({x:.3f}, {y:.3f}) m, "
            f"direction {action['pd_rad'] * 57.2958:.0f} deg, {episode['steps']} steps"
        )
        if "object_displacement_m" in episode:
            text += f", object moved {max(episode['object_displacement_m']) * 100:.1f} cm"
        if "peak_tactile_force_n" in episode:
            text += f", peak force {episode['peak_tactile_force_n']:.2f} N"
        lines.append(text)
    for blocked in summary.get("blocked_actions", []):
        (x, y), z = blocked["point_m"], blocked["blocked_at_m"][2]
        lines.append(
            f"  not carried out: {blocked['kind']} at ({x:.3f}, {y:.3f}) m, direction "
            f"{blocked['pd_rad'] * 57.2958:.0f} deg, its way down blocked at {z:.3f} m height"
        )
    if summary.get("shape"):
        lines += _shape_lines(summary["shape"], summary.get("shape_errors") or {})
    if summary.get("touch_errors"):
        lines.append(_touch_line(summary.get("touch") or {}, summary["touch_errors"]))
    if summary.get("learned_shape"):
        lines.append(_learned_line(summary["learned_shape"]))
    if summary.get("goal_push"):
        lines.append(_goal_line(summary["goal_push"]))
    lines += [_change_line(report) for report in summary.get("change_detection", [])]
    if summary.get("belief"):
        lines.append(
            _belief_table(
                summary["belief"],
                summary.get("belief_truth")
                or (summary.get("ground_truth") or {}).get("parameters", {}),
            )
        )
    if summary.get("belief_truth"):
        lines.append(
            "  (truth: the true link nearest each belief link; the CoM in the belief's frame "
            "of that link, where the belief puts it at the end)"
        )
    lines.append(f"  data: {out_dir}/ ({', '.join(_written(out_dir))})")
    return "\n".join(lines)


def _written(out_dir: Path) -> list[str]:
    """The run files and folders in ``out_dir`` (a folder with a trailing /)."""
    from vistac.recording import RUN_DIRS, RUN_FILES

    return [f"{name}/" if (out_dir / name).is_dir() else name
            for name in (*RUN_FILES, *RUN_DIRS) if (out_dir / name).exists()]  # fmt: skip


def _touch_line(touch: dict[str, Any], errors: dict[str, Any]) -> str:
    """The touch result: most likely class, whether it is right, the pose error, steps."""
    if touch.get("mle_class") is None:
        return f"  touch: nothing recognised in {errors.get('steps')} touches"
    verdict = "right" if errors.get("class_correct") else "wrong"
    pose_m = errors.get("pose_error_m")
    pose = "no pose" if pose_m is None else f"pose error {1e3 * pose_m:.1f} mm"
    return (
        f"  touch: {touch.get('mle_class')} ({verdict} class), {pose}, "
        f"{errors.get('steps')} touches, at most {errors.get('max_particle_count')} particles"
    )


def _learned_line(record: dict[str, Any]) -> str:
    """Where the learned shape went and its reconstruction error, or why it was not saved."""
    if not record.get("saved"):
        return f"  learned shape: not saved ({record.get('reason')})"
    text = f"  learned shape: saved to {record.get('path')}"
    if record.get("reconstruction_error_m") is not None:
        text += f", TWD to the true shape {1e3 * record['reconstruction_error_m']:.1f} mm"
    if record.get("poisson_error_m") is not None:
        text += f" (screened Poisson {1e3 * record['poisson_error_m']:.1f} mm)"
    return text


def _goal_line(record: dict[str, Any]) -> str:
    """Whether link 0 reached the goal, after how many planned pushes, and how far from it
    the belief and (in simulation) the truth put it."""
    x, y, turn = record["goal"]
    text = f"  goal ({x:.3f}, {y:.3f}) m, turn {math.degrees(turn):.0f} deg: "
    pushes = len(record.get("planned_cost_m", []))
    if "reached" not in record:
        return text + f"not checked ({pushes} goal push(es) planned)"
    text += f"{'reached' if record['reached'] else 'not reached'} after {pushes} goal push(es)"
    text += (
        f"; link 0 believed {1e3 * record['believed_error_m']:.1f} mm, "
        f"{math.degrees(record['believed_turn_error_rad']):.0f} deg from it"
    )
    if "true_error_m" in record:
        text += (
            f", truly {1e3 * record['true_error_m']:.1f} mm, "
            f"{math.degrees(record['true_turn_error_rad']):.0f} deg"
        )
    return text


def _change_line(report: dict[str, Any]) -> str:
    """One interaction's change report: its lowest window score and whether it was flagged."""
    text = f"  episode {report['episode']}: likelihood score {report['score']:.2f}, "
    if report["flagged"]:
        return text + f"change flagged {report['flagged_after_s']:.1f} s after its start"
    return text + "no change"


def _shape_lines(shape: dict[str, Any], errors: dict[str, Any]) -> list[str]:
    """One line per fitted link: semi-axes, exponents, pose; then the Chamfer distances."""
    lines = [f"  shape: {len(shape['links'])} link(s) in {shape['time_s']:.2f} s"]
    for index, link in enumerate(shape["links"]):
        a1, a2, a3 = (1e3 * v for v in link["superquadric"]["scale_m"])
        eps1, eps2 = link["superquadric"]["exponents"]
        x, y, theta = link["initial_pose"]
        lines.append(
            f"    link {index}: semi-axes {a1:.1f} x {a2:.1f} x {a3:.1f} mm, "
            f"eps ({eps1:.2f}, {eps2:.2f}), at ({x:.3f}, {y:.3f}) m, {theta * 57.2958:.0f} deg"
        )
    if errors.get("chamfer_m"):
        values = ", ".join("-" if c is None else f"{1e3 * c:.2f}" for c in errors["chamfer_m"])
        lines.append(f"    Chamfer distance to the true links: {values} mm")
    return lines


def _belief_table(belief: dict[str, dict[str, float]], truth: dict[str, float]) -> str:
    rows = [f"  {'parameter':<12}{'estimate':>10}{'std':>10}{'truth':>10}"]
    for name, entry in belief.items():
        true = f"{truth[name]:>10.4f}" if name in truth else f"{'-':>10}"
        rows.append(f"  {name:<12}{entry['mean']:>10.4f}{entry['std']:>10.4f}{true}")
    return "\n".join(rows)


def cmd_validate(args: argparse.Namespace) -> int:
    from vistac.skill import load_skill

    plugins = _plugins(args)
    worst = 0
    for path in args.files:
        try:
            load_skill(path, plugins.registry, args.set)
        except ConfigError as exc:
            for line in str(exc).splitlines():
                print(f"error: {line}", file=sys.stderr)
            worst = max(worst, exc.exit_code)
            continue
        print(f"{path}: ok")
    return worst


def cmd_plugins(args: argparse.Namespace) -> int:
    plugins = _plugins(args)
    entries = plugins.registry.entries()
    if args.json:
        print(
            json.dumps(
                {
                    "plugins": plugins.loaded,
                    "failures": [{"name": f.name, "error": f.error} for f in plugins.failures],
                    "components": [e.__dict__ for e in entries],
                },
                indent=2,
            )
        )
        return 0
    print("plugins: " + ", ".join(plugins.loaded))
    for failure in plugins.failures:
        print(f"failed:  {failure.name}: {failure.error}")
    kind = None
    for entry in entries:
        if entry.kind != kind:
            kind = entry.kind
            print(f"\n{kind}:")
        print(f"  {entry.name:<24} {entry.target}  [{entry.plugin}]")
    return 0


def cmd_schema(args: argparse.Namespace) -> int:
    from vistac.schema import skill_schema

    print(json.dumps(skill_schema(_plugins(args).registry), indent=2))
    return 0


def cmd_tree(args: argparse.Namespace) -> int:
    import py_trees
    from vistac.skill import load_skill
    from vistac.tree import build_tree

    skill = load_skill(args.skill, _plugins(args).registry, args.set)
    print(py_trees.display.unicode_tree(build_tree(skill.tree, None)))
    return 0


def cmd_objects_generate(args: argparse.Namespace) -> int:
    from vistac.objects import write_configurations
    from vistac.recording import refuse_file_as_folder

    refuse_file_as_folder(args.out)
    split = write_configurations(args.seed, args.out)
    counts = ", ".join(f"{len(names)} {part}" for part, names in split.items())
    print(
        f"wrote {sum(map(len, split.values()))} object configurations ({counts}) "
        f"and split.json to {args.out}"
    )
    return 0


def cmd_objects_hinges(args: argparse.Namespace) -> int:
    import dataclasses
    import math

    from vistac.objects import generate_configurations, load_object
    from vistac.plugins.filters.evaluate import OBJECT_SET_SEED
    from vistac.plugins.filters.hinges import hinge_turns, hinges_markdown
    from vistac.recording import write_json

    if args.out is not None and args.out.is_dir():
        raise ConfigError(f"--out {args.out} is a folder; give a file, e.g. "
                          f"{args.out / 'hinges.json'}")  # fmt: skip
    specs = []
    for item in args.objects:
        if item == "generated":
            generated = generate_configurations(OBJECT_SET_SEED)
            specs += [spec for spec in generated if spec.type == "articulated"]
        else:
            specs.append(load_object(item))
    unhinged = [f"{spec.name} ({spec.type})" for spec in specs if spec.joint is None]
    if unhinged:
        raise ConfigError(f"{', '.join(unhinged)}: no hinge to turn; give articulated objects")
    results = {}
    for spec in specs:
        assert spec.joint is not None
        friction = spec.joint.friction_nm if args.joint_friction is None else args.joint_friction
        results[spec.name] = (friction, hinge_turns(spec, args.joint_friction))
    print("\n".join(hinges_markdown(results, math.radians(args.threshold_deg))))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.out, {name: {"joint_friction_nm": friction,
                                     "pushes": [dataclasses.asdict(p) for p in pushes]}
                              for name, (friction, pushes) in results.items()})  # fmt: skip
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    existed = args.out.exists()
    try:
        return _train(args)
    except BaseException:
        if not existed and args.out.is_dir() and not any(args.out.iterdir()):
            args.out.rmdir()  # nothing written: leave no empty folder behind
        raise


def _train(args: argparse.Namespace) -> int:
    from vistac.plugins.filters.train import load_preset, train
    from vistac.recording import refuse_file_as_folder

    if not args.skill.is_file():
        raise ConfigError(f"{args.skill}: no such collection skill file")
    refuse_file_as_folder(args.out)
    if args.selection is not None:
        return _train_active(args)
    active_only = [f"--{name.replace('_', '-')}" for name in ("rounds", "threshold", "per_round")
                   if getattr(args, name) is not None]  # fmt: skip
    if active_only:
        raise ConfigError(f"{', '.join(active_only)}: only with --selection (active training)")
    report = train(args.skill, args.out, load_preset(args.preset), args.data or None)
    print(f"trained in {report['time_s']:.0f} s; checkpoints and train.json in {args.out}")
    return 0


def _train_active(args: argparse.Namespace) -> int:
    from vistac.plugins.filters.active import active_settings, summary_lines, train_active
    from vistac.plugins.filters.train import load_preset

    if args.data:
        raise ConfigError("--data: active training collects its own data; drop --data")
    config = load_preset(args.preset)  # checks the preset before its active block is read
    active = active_settings(
        args.preset, selection=args.selection, max_rounds=args.rounds,
        threshold=args.threshold, per_round=args.per_round,
    )  # fmt: skip
    report = train_active(args.skill, args.out, config, active)
    for line in summary_lines(report):
        print(line)
    print(f"trained in {report['time_s']:.0f} s; checkpoints, train.json and "
          f"active_training.png in {args.out}")  # fmt: skip
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from vistac.plugins.filters.evaluate import compare_evaluations, differences_markdown

    table = compare_evaluations(args.base, args.other)
    print("\n".join(differences_markdown(
        table, f"{args.other} minus {args.base} (overall NRMSE)",
        f"Each variant's overall NRMSE in {args.other} minus in {args.base} on the objects "
        f"both ran (negative: lower in {args.other})",
    )))  # fmt: skip
    return 0


def cmd_information(args: argparse.Namespace) -> int:
    import dataclasses
    import math

    from vistac.plugins.filters.information import (
        WINDOW_STEPS,
        ModelError,
        collect_information,
        information_markdown,
        information_tables,
        model_markdown,
        model_reports,
        run_folders,
        skill_model,
    )
    from vistac.recording import write_json

    error = ModelError()
    error = ModelError(
        args.position_error_m or error.position_m,
        math.radians(args.angle_error_deg) if args.angle_error_deg else error.angle_rad,
        args.force_error_n or error.force_n,
    )
    if args.out is not None and args.out.is_dir():
        raise ConfigError(f"--out {args.out} is a folder; give a file, e.g. "
                          f"{args.out / 'information.json'}")  # fmt: skip
    model = None if args.skill is None else skill_model(args.skill, args.set, _plugins(args))
    runs = run_folders(args.folder, args.variant)
    by_type = collect_information(runs)
    reports = {} if model is None else model_reports(by_type, model, error)
    own = {kind: report.repeating_error for kind, report in reports.items()}
    tables = information_tables(by_type, error, args.scale, own)
    lines = information_markdown(tables, error) + (model_markdown(reports) if reports else [])
    report: dict[str, Any] = {
        "runs": [str(run) for run in runs], "model_error": dataclasses.asdict(error),
        "window_steps": WINDOW_STEPS, "tables": tables,
        "model": {kind: dataclasses.asdict(reports[kind]) for kind in reports},
    }  # fmt: skip
    print("\n".join(lines))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json(args.out, report)
    return 0


def cmd_eval(args: argparse.Namespace) -> int:
    from vistac.plugins.actions.campaign import is_goal_skill
    from vistac.plugins.filters.evaluate import (
        EvalOptions,
        evaluate,
        parse_models,
        parse_variants,
        read_skill,
    )
    from vistac.plugins.touch.campaign import is_touch_skill
    from vistac.recording import refuse_file_as_folder

    if not args.skill.is_file():
        raise ConfigError(f"{args.skill}: no such skill file")
    read_skill(args.skill)  # malformed or not a mapping: one clear line
    refuse_file_as_folder(args.out)
    kind = "parameter-estimation"
    if is_touch_skill(args.skill):
        kind = "touch"
    elif is_goal_skill(args.skill):
        kind = "goal-push"
    _refuse_unused_eval_options(args, kind)
    if kind == "touch":
        return _eval_touch(args)
    if kind == "goal-push":
        return _eval_goal(args)
    options = EvalOptions(
        skill=args.skill, out=args.out, objects=tuple(args.objects),
        checkpoints=args.checkpoints, models=parse_models(args.models or DEFAULT_MODELS),
        variants=parse_variants(args.variants or DEFAULT_VARIANTS),
        max_objects=args.max_objects, max_interactions=args.max_interactions, seed=args.seed,
        overrides=tuple(args.set), paired=args.paired,
    )  # fmt: skip
    if args.checkpoints is not None and not args.checkpoints.is_dir():
        raise ConfigError(f"--checkpoints: {args.checkpoints} is not a folder")
    report = evaluate(options)
    print((args.out / "tables.md").read_text(encoding="utf-8"))
    skipped = [r for r in report["runs"] if r["status"] != "ok"]
    for run in skipped:
        print(f"{run['status']}: {run['variant']} on {run['object']}: {run['reason']}")
    print(f"evaluated {len(report['runs']) - len(skipped)} runs; eval.json, tables and plots "
          f"in {args.out}")  # fmt: skip
    return 1 if any(run["status"] == "failed" for run in skipped) else 0


DEFAULT_MODELS = "gnn,ff,analytical,physics"
DEFAULT_VARIANTS = "a-gnn,u-gnn,r-gnn,a-ff,a-analytical,gnn-fixed"
DEFAULT_TRIALS = 10
DEFAULT_EXPLORERS = "dhd,rrt"
_EVAL_OPTION_KINDS = {
    "checkpoints": ("parameter-estimation",), "models": ("parameter-estimation",),
    "variants": ("parameter-estimation",), "max_objects": ("parameter-estimation",),
    "max_interactions": ("parameter-estimation",), "paired": ("parameter-estimation",),
    "trials": ("touch", "goal-push"), "explorers": ("touch",),
}  # fmt: skip
"""The skills (parameter estimation, touch, goal-push) each ``vistac eval`` option acts on."""


def _refuse_unused_eval_options(args: argparse.Namespace, kind: str) -> None:
    """ConfigError naming each option given that a ``kind`` skill's evaluation ignores."""
    unused = [
        f"--{name.replace('_', '-')} (only for {' and '.join(kinds)} skills)"
        for name, kinds in _EVAL_OPTION_KINDS.items()
        if kind not in kinds and getattr(args, name) not in (None, False)
    ]
    if unused:
        raise ConfigError(
            f"{args.skill} is a {kind} skill; its evaluation does not use {', '.join(unused)}; "
            f"leave {'it' if len(unused) == 1 else 'them'} out"
        )


def _trials(args: argparse.Namespace) -> int:
    return DEFAULT_TRIALS if args.trials is None else int(args.trials)


def _eval_touch(args: argparse.Namespace) -> int:
    from vistac.plugins.touch.campaign import TouchEvalOptions, evaluate_touch, parse_explorers

    objects = ("known",) if args.objects == ["test"] else tuple(args.objects)
    options = TouchEvalOptions(
        skill=args.skill, out=args.out, objects=objects, trials=_trials(args),
        explorers=parse_explorers(args.explorers or DEFAULT_EXPLORERS),
        seed=args.seed if args.seed is not None else 0, overrides=tuple(args.set),
    )  # fmt: skip
    return _print_campaign(evaluate_touch(options), args.out, "explorer", "touch")


def _eval_goal(args: argparse.Namespace) -> int:
    from vistac.plugins.actions.campaign import GoalEvalOptions, evaluate_goal

    objects = ("all",) if args.objects == ["test"] else tuple(args.objects)
    options = GoalEvalOptions(
        skill=args.skill, out=args.out, objects=objects, trials=_trials(args), seed=args.seed,
        overrides=tuple(args.set),
    )  # fmt: skip
    return _print_campaign(evaluate_goal(options), args.out, "mode", "goal-push")


def _print_campaign(report: dict[str, Any], out: Path, variant: str, what: str) -> int:
    """Print the tables of a campaign, its failed runs (``variant`` names what varies besides
    the object and trial) and where the files are; the exit code: 1 when a run failed."""
    print((out / "tables.md").read_text(encoding="utf-8"))
    failed = [r for r in report["records"] if r["status"] != "ok"]
    for record in failed:
        print(f"failed: {record[variant]} on {record['object']} trial {record['trial']}: "
              f"{record['reason']}")  # fmt: skip
    print(f"evaluated {len(report['records']) - len(failed)} {what} runs; eval.json and "
          f"tables.md in {out}")  # fmt: skip
    return 1 if failed else 0


def _seed(text: str) -> int:
    """A ``--seed`` value: an integer from 0 to ``MAX_SEED`` (argparse names the option when
    not)."""
    from vistac.skill import MAX_SEED

    try:
        seed = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid int value: {text!r}") from None
    if seed < 0:
        raise argparse.ArgumentTypeError(f"{seed} is negative; give 0 or more")
    if seed > MAX_SEED:
        raise argparse.ArgumentTypeError(f"{seed} is too large; give at most {MAX_SEED}")
    return seed


def _finite(text: str, least: float, above: bool) -> float:
    """A finite number above (or from) ``least`` (argparse names the option when not)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid number: {text!r}") from None
    if not (value > least if above else value >= least) or value == float("inf"):
        limit = f"above {least:g}" if above else f"of {least:g} or more"
        raise argparse.ArgumentTypeError(f"{text} is not a finite number {limit}")
    return value


def _positive(text: str) -> float:
    return _finite(text, 0.0, above=True)


def _non_negative(text: str) -> float:
    return _finite(text, 0.0, above=False)


def _add_skill_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a key, e.g. components.arm.with.max_speed_mps=0.01",
    )


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="vistac", description=__doc__.splitlines()[0] if __doc__ else ""
    )
    parser.add_argument("--version", action="version", version=f"vistac {__version__}")
    parser.add_argument(
        "-p",
        "--plugin",
        action="append",
        default=[],
        metavar="NAME",
        help="load this plugin (entry-point name or module), also when "
        "VISTAC_DISABLE_PLUGIN_AUTOLOAD=1",
    )
    parser.add_argument("-q", "--quiet", action="store_true", help="only warnings and errors")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a skill")
    run.add_argument("skill", type=Path)
    run.add_argument("--out", type=Path, required=True, help="output folder")
    run.add_argument("--seed", type=_seed, default=None, help="override the skill's seed")
    run.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    _add_skill_options(run)
    run.set_defaults(func=cmd_run)

    replay = sub.add_parser(
        "replay",
        help="feed a recorded run's interactions through its filter again, offline (change "
        "the filter or model with --set)",
    )
    replay.add_argument("run", type=Path, help="folder of an earlier `vistac run`")
    replay.add_argument("--out", type=Path, required=True, help="output folder")
    replay.add_argument("--overwrite", action="store_true", help="replace an earlier run in --out")
    _add_skill_options(replay)
    replay.set_defaults(func=cmd_replay)

    validate = sub.add_parser("validate", help="check skill files without running them")
    validate.add_argument("files", type=Path, nargs="+")
    _add_skill_options(validate)
    validate.set_defaults(func=cmd_validate)

    plugins = sub.add_parser("plugins", help="list plugins and components by kind")
    plugins.add_argument("--json", action="store_true")
    plugins.set_defaults(func=cmd_plugins)

    schema = sub.add_parser("schema", help="print the JSON Schema of skill files")
    schema.set_defaults(func=cmd_schema)

    tree = sub.add_parser("tree", help="print a skill's behaviour tree")
    tree.add_argument("skill", type=Path)
    _add_skill_options(tree)
    tree.set_defaults(func=cmd_tree)

    train = sub.add_parser("train", help="collect interactions in simulation and train models")
    train.add_argument("skill", type=Path, help="the collection skill, e.g. collect_pushes.yaml")
    train.add_argument("--out", type=Path, required=True, help="checkpoint folder")
    train.add_argument(
        "--preset", default="tiny", help="tiny, ship, ship_ff, paper or a preset YAML file"
    )
    train.add_argument(
        "--data",
        type=Path,
        nargs="+",
        action="extend",
        help="train on recorded data instead of collecting: run folders, or the data/ folder "
        "of an earlier training (its train/val split kept)",
    )
    train.add_argument(
        "--selection", choices=("info_gain", "uniform", "random"),
        help="active iterative training: rounds of interactions chosen by this selector, "
        "training on a replay buffer until the validation error reaches the threshold "
        "(info_gain needs a skill with a filter, e.g. explore_active.yaml)",
    )  # fmt: skip
    train.add_argument("--rounds", type=int, help="active: most training rounds (seed included)")
    train.add_argument("--threshold", type=float, help="active: validation error to reach")
    train.add_argument("--per-round", type=int, help="active: interactions per object per round")
    train.set_defaults(func=cmd_train)

    evaluate = sub.add_parser(
        "eval", help="compare the process models on a set of objects; for a touch skill, "
        "recognition over objects x random poses x explorers; for a goal-push skill, the final "
        "error with estimated vs default parameters over objects x trials",
    )  # fmt: skip
    evaluate.add_argument("skill", type=Path, help="the exploration skill, e.g. explore_push.yaml")
    evaluate.add_argument("--out", type=Path, required=True, help="evaluation folder")
    evaluate.add_argument(
        "--objects", nargs="+", default=["test"], metavar="SPLIT|YAML",
        help="test, val, train (the generated set) or object YAML files; for touch skills "
        "known, novel, class names or mesh files (default known); for goal-push skills names "
        "in the skill's objects/ folder, comma-separated, or all (default all)",
    )  # fmt: skip
    evaluate.add_argument(
        "--checkpoints",
        type=Path,
        help="a `vistac train` folder (default: the skill's checkpoints/)",
    )
    evaluate.add_argument(
        "--models", default=None,
        help=f"comma-separated; evaluate only the variants of these process models (default "
        f"{DEFAULT_MODELS})",
    )  # fmt: skip
    evaluate.add_argument(
        "--variants", default=None,
        help="comma-separated model x action selector columns: a-gnn (info gain), u-gnn "
        "(uniform), r-gnn (random), a-ff, a-analytical, gnn-fixed (no parameter estimation), "
        "a-physics (the simulator as the process model; with --paired only); default all but "
        "a-physics",
    )  # fmt: skip
    evaluate.add_argument(
        "--max-objects", type=int, default=None, help="evaluate at most N objects"
    )
    evaluate.add_argument(
        "--max-interactions", type=int, default=None, help="cap on interactions per run"
    )
    evaluate.add_argument("--seed", type=_seed, default=None, help="override the skill's seed")
    evaluate.add_argument(
        "--paired", action="store_true",
        help="variants with the first variant's action selector (a-ff, a-analytical after "
        "a-gnn) and those that do not estimate parameters (gnn-fixed) filter its recorded "
        "interactions (vistac replay) instead of their own: compared on the same pushes",
    )  # fmt: skip
    evaluate.add_argument(
        "--trials", type=int, default=None,
        help=f"touch and goal-push skills: trials per object (seeds SEED .. SEED + N - 1; "
        f"default {DEFAULT_TRIALS})",
    )  # fmt: skip
    evaluate.add_argument(
        "--explorers", default=None,
        help=f"touch skills: comma-separated, dhd and/or rrt (default {DEFAULT_EXPLORERS})",
    )
    _add_skill_options(evaluate)
    evaluate.set_defaults(func=cmd_eval)

    about = ("two `vistac eval` folders of the same objects (say, two trainings' checkpoints): "
             "each variant's overall NRMSE in OTHER minus BASE, with a 90 % interval from "
             "resampling the objects")  # fmt: skip
    compare = sub.add_parser("compare", help=about.replace("%", "%%"), description=about)
    compare.add_argument("base", type=Path, help="the --out folder of one `vistac eval`")
    compare.add_argument("other", type=Path, help="the --out folder of another")
    compare.set_defaults(func=cmd_compare)

    about = ("replay a simulated run's pushes (or those of one `vistac eval` column) with each "
             "parameter moved, and print what they show: the expected NRMSE of a process "
             "model that moved with the parameters as the simulator does and erred by the "
             "given model error per 25-step window")  # fmt: skip
    information = sub.add_parser("information", help=about, description=about)
    information.add_argument("folder", type=Path, help="a run folder or a `vistac eval` --out")
    information.add_argument(
        "--variant", default="a-gnn", help="the evaluation column whose runs to replay"
    )
    information.add_argument(
        "--scale", type=_positive, nargs="+", default=[1.0, 0.5, 0.25],
        help="multiples of the model error to tabulate (default 1 0.5 0.25)",
    )  # fmt: skip
    for option, what in (("--position-error-m", "each link's position (default 0.007)"),
                         ("--angle-error-deg", "each link's angle (default 2.5)"),
                         ("--force-error-n", "the mean finger force per axis (default 0.8)")):
        information.add_argument(option, type=_positive, help=f"model error of {what}")
    information.add_argument(
        "--skill", type=Path,
        help="also compare this skill's process model (components.model) with the simulator: "
        "how its predictions move with each parameter",
    )  # fmt: skip
    information.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="override a key of --skill, e.g. components.model.with.checkpoint=other.pt",
    )  # fmt: skip
    information.add_argument("--out", type=Path, help="also write the tables to this JSON file")
    information.set_defaults(func=cmd_information)

    objects = sub.add_parser("objects", help="object configurations")
    objects_sub = objects.add_subparsers(dest="objects_command", required=True)
    generate = objects_sub.add_parser("generate", help="write the 120 configurations and split")
    generate.add_argument("--seed", type=_seed, default=0)
    generate.add_argument("--out", type=Path, required=True)
    generate.set_defaults(func=cmd_objects_generate)
    hinges = objects_sub.add_parser(
        "hinges", help="push hinged objects square to the chain in the simulated world and "
        "report which pushes turn the hinge (a hinge that holds shows only a bound)",
    )  # fmt: skip
    hinges.add_argument(
        "objects", nargs="+", metavar="YAML|generated",
        help="articulated object files, or `generated`: the 40 articulated objects of "
        "`vistac objects generate` (seed 0)",
    )  # fmt: skip
    hinges.add_argument(
        "--joint-friction", type=_non_negative, default=None, metavar="NM",
        help="set every hinge's friction to this (N m) instead of the object's",
    )  # fmt: skip
    hinges.add_argument("--threshold-deg", type=_positive, default=3.0,
                        help="a turn farther than this counts as turned (default 3)")  # fmt: skip
    hinges.add_argument("--out", type=Path, help="also write every push to this JSON file")
    hinges.set_defaults(func=cmd_objects_hinges)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    _setup_logging(args.quiet, args.verbose)
    keep_freed_memory()
    func: Callable[[argparse.Namespace], int] = args.func
    try:
        return func(args)
    except VistacError as exc:
        for line in str(exc).splitlines():
            print(f"error: {line}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # The reader went away (`vistac plugins | head`): no traceback, and no second
        # error when the interpreter flushes stdout on exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


if __name__ == "__main__":
    sys.exit(main())
