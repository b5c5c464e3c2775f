"""The `scissor` command line: thin wrappers over the pipeline modules.

Exit codes (docs/contract.md#exit-codes-and-messages): 0 success; 2 bad
config or arguments, one message, no traceback; 1 a failure at run time,
with the reason; 128 + N when `simulate` is stopped by signal N (130 Ctrl-C,
143 SIGTERM).
"""

from __future__ import annotations

import dataclasses
import datetime as _dt
import faulthandler
import inspect
import os
import signal
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from scissor_cli import __version__, progress, runtime
from scissor_cli.config import Config, ConfigError, load_config, parse_config, resolved_yaml

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="scissor: simulate robot-assisted breast intervention from a YAML scene.",
)
err = Console(stderr=True, highlight=False)
out = Console(highlight=False)

DEFAULT_SCENE = Path(__file__).parent / "scenes" / "example.yaml"
#: --jobs: more worker processes than this only thrash; --samples: the sample array is held whole in memory
MAX_JOBS, MAX_SAMPLES = 256, 20_000_000


class ConsoleReporter:
    """Messages and progress bars on stderr; silent with --quiet, bars only on a terminal."""

    def __init__(self, quiet: bool):
        self.quiet = quiet
        self.bars = not quiet and err.is_terminal

    def info(self, message: str) -> None:
        if not self.quiet:
            err.print(message)

    def progress(self, description: str, total: int) -> Callable[[int], None]:
        if not self.bars or total <= 1:
            return lambda advance=1: None
        bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                       TextColumn("eta"), TimeRemainingColumn(), console=err, transient=True)
        task = bar.add_task(description, total=total)
        bar.start()

        def advance(n: int = 1) -> None:
            bar.advance(task, n)
            if bar.finished:
                bar.stop()

        return advance


def _fail(code: int, message: str) -> None:
    # a file name or YAML key may hold lone surrogates (undecodable bytes): show them escaped
    message = message.encode("utf-8", "backslashreplace").decode("utf-8")
    if code == 1:
        err.print(f"[bold red]error:[/] {escape(message)}", soft_wrap=True, emoji=False)
    else:
        err.print(f"error: {message}", markup=False, soft_wrap=True, emoji=False)
    raise typer.Exit(code)


def _load(config: Optional[Path]) -> tuple[Config, str]:
    path = config or DEFAULT_SCENE
    try:
        cfg = load_config(path)
    except ConfigError as exc:
        _fail(2, str(exc))
    if cfg.tissue.shape in ("dome", "surface"):  # a 3-D scene's element budget and cameras
        from scissor_cli.experiments.body_scene_checks import body_scene_problems

        problems = body_scene_problems(cfg)
        if problems:
            _fail(2, f"{path}: {problems[0]}" + (f"\n  (and {len(problems) - 1} more problem(s))"
                                                 if len(problems) > 1 else ""))
    return cfg, path.stem


def _out_dir(out: Optional[Path], stem: str, force: bool) -> Path:
    if out is None:
        out = Path("runs") / f"{stem}-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not force:
        _fail(2, f"--out {out}: exists and is not empty; choose another directory or pass --force")
    return out


def _version(value: bool) -> None:
    if value:
        out.print(f"scissor {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
) -> None:
    """scissor: simulate robot-assisted breast intervention from a YAML scene."""
    try:
        runtime.configure()
    except ValueError as exc:  # (a SCISSOR_THREADS it does not take)
        _fail(2, str(exc))
    if hasattr(signal, "SIGUSR1"):  # `kill -USR1 PID`: every thread's stack on stderr, the run goes on
        try:  # (the process's own stderr: a caller may have put an object without a file descriptor in sys.stderr)
            faulthandler.register(signal.SIGUSR1, file=sys.__stderr__, all_threads=True)
        except (AttributeError, ValueError, OSError):  # no stderr at all (an embedding without one)
            pass


@app.command()
def validate(config: Path = typer.Argument(..., help="Scene YAML file.")) -> None:
    """Validate a scene and print it with every default filled in."""
    cfg, _ = _load(config)
    sys.stdout.write(resolved_yaml(cfg))  # plain: a rich console would wrap long YAML lines


@dataclass(frozen=True)
class SimulateOptions:
    """The options of `scissor simulate` (docs/contract.md#simulate), as one value."""

    config: Optional[Path] = typer.Argument(None, help="Scene YAML file (default: the shipped example scene).")
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Output directory (default runs/<config-stem>-<time>/).")
    trials: Optional[int] = typer.Option(None, "--trials", min=0, max=10_000,
                                         help="Trials per target (0: forward cases and plans only).")
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**63 - 1, help="Override the config's seed.")
    solver: Optional[str] = typer.Option(None, "--solver", help="Override the config's solver: admm | newton.")
    truth: Optional[str] = typer.Option(None, "--truth",
                                        help="Override trials.truth: layer | slab (the 3-D slab of layer_check).")
    jobs: Optional[int] = typer.Option(None, "--jobs", min=1, max=MAX_JOBS,
                                       help="Worker processes for trials (default: all cores).")
    executor: str = typer.Option("local", "--executor", help="Where trials run: local | dask.")
    scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address (with --executor dask).")
    resume: Optional[Path] = typer.Option(
        None, "--resume", help="Finish an interrupted run directory: the stages it had not finished, then its trials.")
    study: bool = typer.Option(False, "--study",
                               help="Also run the solver study (the config's `study` section or its defaults).")
    budget: bool = typer.Option(
        False, "--budget", help="Also run the error budget: the trials again with one error source at a time.")
    force: bool = typer.Option(False, "--force", help="Write into a non-empty --out directory.")
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress or messages, only the output path.")


def takes_options(options_cls):
    """A typer command whose parameters are the fields of the dataclass `options_cls`; the body gets one value of it.

    typer reads a command's parameters from its signature, so the command
    is given the fields' signature; the options are declared once, with
    their help, on the dataclass.
    """

    def decorate(body):
        hints = typing.get_type_hints(options_cls)
        fields = dataclasses.fields(options_cls)

        def command(**values):
            return body(options_cls(**values))

        command.__signature__ = inspect.Signature([
            inspect.Parameter(f.name, inspect.Parameter.POSITIONAL_OR_KEYWORD, default=f.default,
                              annotation=hints[f.name])
            for f in fields])
        command.__annotations__ = {f.name: hints[f.name] for f in fields}
        command.__name__, command.__doc__ = body.__name__, body.__doc__
        return command

    return decorate


@app.command()
@takes_options(SimulateOptions)
def simulate(options: SimulateOptions) -> None:
    """Mesh the scene, solve its forward cases, plan the needle, manipulate the targets, run trials."""
    from scissor_cli.experiments.pool import install_signal_handlers
    from scissor_cli.experiments.simulate import Execution

    if options.executor not in ("local", "dask"):
        _fail(2, f"--executor: must be 'local' or 'dask'; got {options.executor!r}")
    if options.executor == "dask" and not options.scheduler:
        _fail(2, "--executor dask needs --scheduler ADDRESS (e.g. tcp://127.0.0.1:8786)")
    execution = Execution(options.jobs or os.cpu_count() or 1, options.executor, options.scheduler)
    install_signal_handlers()  # SIGTERM, SIGINT, SIGHUP: stop the workers, keep what finished, exit 128 + N
    with progress.reporting(ConsoleReporter(options.quiet)):
        if options.resume is not None:
            _resume(options.resume, execution)
        else:
            _new_run(options, execution)


def _resume(directory: Path, execution) -> None:
    """`simulate --resume DIR`: finish the run in DIR."""
    from scissor_cli.experiments.pool import WorkerLost
    from scissor_cli.experiments.simulate import NonFiniteError, ResumeError, TrialsFailed, resume_simulation
    from scissor_cli.output.results_sink import STARTED, open_for_resume, started_config
    from scissor_cli.output.run_lock import RunBusy, claim

    try:
        lock = claim(directory) if directory.is_dir() else None  # noqa: F841 (held to the process's end)
        try:
            sink = open_for_resume(directory)
        except ResumeError:
            started = started_config(directory)
            if started is None:
                raise
            cfg = parse_config(started, str(directory / STARTED))
            progress.info(f"--resume {directory}: the run stopped before it wrote results.h5; it starts again "
                          f"from its config ({STARTED})")
            _run(cfg, directory, execution, directory / STARTED)
            return
        n = resume_simulation(sink, execution)
    except (ResumeError, ConfigError, RunBusy) as exc:  # also: the run's own config no longer validates
        _fail(2, str(exc))
    except (TrialsFailed, NonFiniteError, WorkerLost) as exc:
        err.print(f"results so far: {directory / 'results.h5'} (status = failed)")
        _fail(1, str(exc))
    except KeyboardInterrupt as exc:
        _stopped(exc, directory, f"resume again with: scissor simulate --resume {directory}")
    progress.info(f"resumed: {n} trial(s) run")
    out.print(str(directory))


def _configured(options: SimulateOptions) -> tuple[Config, str]:
    """The scene with the command line's overrides; exit 2 on a bad combination."""
    cfg, stem = _load(options.config)
    scene = options.config or DEFAULT_SCENE
    body = cfg.tissue.shape in ("dome", "surface")
    if body and options.study:
        _fail(2, f"--study: the solver study runs on a 2-D layer; {scene} is a 3-D body (tissue.shape "
                 f"{cfg.tissue.shape})")
    if body and options.truth is not None:
        _fail(2, f"--truth: a 3-D scene's trials run against the body itself; {scene} is a 3-D body")
    if options.solver is not None:
        if options.solver not in ("admm", "newton"):
            _fail(2, f"--solver: must be 'admm' or 'newton'; got {options.solver!r}")
        cfg = cfg.model_copy(update={"solver": cfg.solver.model_copy(update={"kind": options.solver})})
    if options.truth is not None:
        if options.truth not in ("layer", "slab"):
            _fail(2, f"--truth: must be 'layer' or 'slab'; got {options.truth!r}")
        if options.truth == "slab" and cfg.layer_check is None:
            _fail(2, f"--truth slab: {scene} has no layer_check section (the slab to use as the "
                     "truth); add one, e.g. `layer_check: {}` for every default (docs/contract.md, layer_check)")
        cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update={"truth": options.truth})})
    if options.seed is not None:
        cfg = cfg.model_copy(update={"seed": options.seed})
    if options.trials is not None:
        trials = {"count": options.trials}
        if options.trials == 0 and cfg.trials.budget:  # no trials, no budget: the budget reruns the trials
            trials["budget"] = False
        cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update=trials)})
    if options.budget:
        if cfg.trials.count == 0:
            _fail(2, f"--budget: the error budget reruns the trials, and {scene} runs none "
                     f"(trials.count or --trials is 0); give --trials N with N >= 1")
        cfg = cfg.model_copy(update={"trials": cfg.trials.model_copy(update={"budget": True})})
    if options.study and cfg.study is None:
        from scissor_cli.config import StudyConfig

        cfg = cfg.model_copy(update={"study": StudyConfig()})
    try:  # the options may combine with the scene into something it does not allow: say so now, not in a worker
        parse_config(resolved_yaml(cfg), f"{scene} with the command's options")
    except ConfigError as exc:
        _fail(2, str(exc))
    return cfg, stem


def _new_run(options: SimulateOptions, execution) -> None:
    """`simulate [CONFIG]`: a new run in its own directory."""
    from scissor_cli.output.run_lock import RunBusy, claim

    cfg, stem = _configured(options)
    directory = _out_dir(options.out_dir, stem, options.force)
    try:
        lock = claim(directory)  # noqa: F841 (held to the process's end: a second run here would truncate this one's)
    except RunBusy as exc:
        _fail(2, f"--out {exc}")
    _run(cfg, directory, execution, options.config or DEFAULT_SCENE)


def _run(cfg: Config, directory: Path, execution, scene) -> None:
    """A run of cfg from its first stage into `directory` (claimed); its config recorded first for `--resume`."""
    from scissor_cli import api
    from scissor_cli.experiments.pool import WorkerLost
    from scissor_cli.experiments.simulate import NonFiniteError, TrialsFailed
    from scissor_cli.experiments.study import StudyError
    from scissor_cli.mechanics.tissue import BoundaryError
    from scissor_cli.mesh.mesh import MeshError
    from scissor_cli.solvers.common import SolverError

    try:
        summary = api.run(cfg, directory, execution)  # the Python API's run: the CLI adds options and exit codes
    except (BoundaryError, MeshError, StudyError) as exc:
        _fail(2, f"{scene}: {exc}")
    except NotImplementedError as exc:  # the needle planner's inverse kinematics for a custom chain
        _fail(2, f"{scene}: robot.dh: {exc}")
    except (SolverError, TrialsFailed, NonFiniteError, WorkerLost) as exc:
        err.print(f"results so far: {directory / 'results.h5'} (status = failed)", markup=False, soft_wrap=True)
        _fail(1, str(exc))
    except KeyboardInterrupt as exc:
        _stopped(exc, directory, f"finish the run with: scissor simulate --resume {directory}")
    out.print(str(summary.out_dir))


def _stopped(exc: KeyboardInterrupt, directory: Path, how: str) -> None:
    """A stopped `simulate`: where the results are, how to go on, exit 128 + the signal (130 for Ctrl-C)."""
    code = getattr(exc, "exit_code", 130)
    results = directory / "results.h5"
    where = (f"results so far: {results} (status = failed)" if results.is_file()
             else "it stopped before writing any results")
    err.print(f"interrupted ({exc.args[0] if exc.args else 'SIGINT'}); {where}; {how}")
    raise typer.Exit(code)


@app.command()
def workspace(
    config: Optional[Path] = typer.Argument(
        None, help="Scene YAML file for its `robot` section (default: the paper's robot)."),
    samples: int = typer.Option(1_000_000, "--samples", min=1, max=MAX_SAMPLES,
                                help="Joint-space samples (about 0.5 s and 0.2 GB per million)."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Output directory (default runs/workspace-<time>/)."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, max=2**63 - 1,
                                       help="Sampling seed (default: the config's seed, else 0)."),
    grid: bool = typer.Option(False, "--grid", help="Sample a tensor grid instead of uniformly at random."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty --out directory."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Only the output path."),
) -> None:
    """Sample the puncture module's joint space: workspace.h5, the Fig. 8 projections, box coverage."""
    from scissor_cli.output.workspace_file import plot_workspace, write_workspace_h5
    from scissor_cli.robot.chain import RobotModel
    from scissor_cli.robot.workspace import run_workspace

    if config is not None:
        cfg, stem = _load(config)
    else:
        from scissor_cli.config import Config

        cfg, stem = Config(), "workspace"
    try:
        robot = RobotModel.from_config(cfg.robot)
    except ValueError as exc:
        _fail(2, f"{config}: robot.dh: {exc}")
    directory = _out_dir(out_dir, f"{stem}-workspace" if config else "workspace", force)
    directory.mkdir(parents=True, exist_ok=True)
    box = cfg.robot.breast_box_mm
    used_seed = cfg.seed if seed is None else seed
    result = run_workspace(robot, box.min, box.max, samples=samples, seed=used_seed,
                           method="grid" if grid else "uniform", voxel_mm=cfg.robot.voxel_mm)
    write_workspace_h5(directory / "workspace.h5", result, {"scissor_version": __version__, "robot": robot.name})
    plot_workspace(result, directory / "workspace.png")
    reporter = ConsoleReporter(quiet)
    c, r = result.coverage, result.reachable
    reporter.info(f"{result.samples} samples in {result.timings['total_s']:.2f} s; box {box.min} .. {box.max} mm, "
                  f"voxels of {cfg.robot.voxel_mm:g} mm")
    reporter.info(f"coverage (sampled tips): {100 * c.coverage:.1f}% of the box, "
                  f"{100 * c.coverage_multi_direction:.1f}% from >= 3 insertion directions")
    if r is not None:
        reporter.info(f"coverage (reachable by IK): {100 * r.coverage:.1f}% of the box, "
                      f"{100 * r.coverage_multi_direction:.1f}% from >= 3 insertion directions")
        if r.coverage < 1:
            reporter.info(r.summary)
    elif c.coverage < 1:
        reporter.info(c.summary)
    out.print(str(directory))


@app.command()
def report(
    run_dirs: list[Path] = typer.Argument(..., help="Run directories (each with a results.h5)."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Where to write (default: runs/report-<time>/)."),
    partial: bool = typer.Option(False, "--partial", help="Also report runs whose status is not 'complete'."),
) -> None:
    """Combine runs: error box plots and summary tables of trials; speed against error of studies."""
    from scissor_cli.output.report import ReportError, make_report

    directory = out_dir or Path("runs") / f"report-{_dt.datetime.now().strftime('%Y%m%d-%H%M%S')}"
    try:
        result = make_report(run_dirs, directory, partial)
    except ReportError as exc:
        _fail(2, str(exc))
    sys.stdout.write(result.table_markdown)
    for path in result.files:
        err.print(f"wrote {path}")


@app.command()
def export(
    run_dir: Path = typer.Argument(..., help="Run directory (with a results.h5)."),
    fmt: str = typer.Option("xdmf", "--format", help="xdmf (.xdmf + .h5) | vtu (.vtu, time series as .pvd)."),
    out_dir: Optional[Path] = typer.Option(None, "--out", help="Where to write (default: RUN_DIR/export/)."),
    partial: bool = typer.Option(False, "--partial", help="Also export a run whose status is not 'complete'."),
    force: bool = typer.Option(False, "--force", help="Write into a non-empty --out directory."),
) -> None:
    """Write the run's mesh, forward cases, insertion steps and 3-D slab as files ParaView opens."""
    from scissor_cli.output.export import FORMATS, ExportError, export_run

    if fmt not in FORMATS:
        _fail(2, f"--format: must be 'xdmf' or 'vtu'; got {fmt!r}")
    directory = _out_dir(out_dir or run_dir / "export", "export", force)
    try:
        written = export_run(run_dir, directory, fmt, partial)
    except ExportError as exc:
        _fail(2, str(exc))
    for item in written:
        out.print(f"{item.path}: {item.what}", markup=False, soft_wrap=True)


def run() -> None:  # pragma: no cover - console entry for `python -m scissor_cli`
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
