"""The one registry of the experiments: each declares its runner and the options it takes (:data:`RUNNERS`); every
servo comparison (each paper's module declares its own) runs through the same runner; planning an experiment on a
scenario and an arm, its runs (side by side with :mod:`.pool`), and its output (:func:`run_experiment`,
:func:`run_experiments`)."""
from __future__ import annotations

import importlib
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

import msgspec

from protocol.conventions import ClockMode
from services.experiments import constraints, mixed_frame, tracking_region
from services.experiments.report import report_markdown, write_results
from services.experiments.spec import Experiment, RunSpec, run_row
from services.paths import SCENARIOS
from services.servo.figures import comparison_plots
from services.experiments.pool import RunTask, run_tasks
from services.runtime.config import ConfigError
from services.servo.result import ServoResult, read_log
from services.servo.scenario import Scenario, load_scenario, on_arm


#: every servo comparison, in the order the command line lists them: each paper's module declares its own
EXPERIMENTS: dict[str, Experiment] = {e.name: e for e in (
    *mixed_frame.EXPERIMENTS, *constraints.EXPERIMENTS, *tracking_region.EXPERIMENTS)}


@dataclass(frozen=True)
class ExperimentRunner:
    """How ``mfvs experiment NAME`` runs an experiment: a function of the command line's arguments that returns the
    exit code (``run``: ``module:function``, imported when it runs), and the options it takes besides everyone's
    (``--json``, ``--out``, ``--arm``, ``--profile``), by their argparse names."""

    name: str
    run: str
    options: tuple[str, ...]

    def function(self) -> Callable:
        module, function = self.run.split(":")
        return getattr(importlib.import_module(module), function)


#: every servo comparison's options; ``random_starts`` and ``seed`` where it declares random starts
SERVO_OPTIONS = ("scenario", "jobs", "processes")
RANDOM_START_OPTIONS = ("random_starts", "seed")


def _runners() -> dict[str, ExperimentRunner]:
    runners = {name: ExperimentRunner(name, "services.cli.commands:servo_experiment",
                                      SERVO_OPTIONS + (RANDOM_START_OPTIONS if experiment.random_starts else ()))
               for name, experiment in EXPERIMENTS.items()}
    runners["torque-control"] = ExperimentRunner("torque-control", "services.cli.commands:torque_experiment",
                                                 ("quick", "runs"))
    runners["markerless"] = ExperimentRunner("markerless", "services.cli.commands:markerless_experiment",
                                             ("scenario", "random_starts", "seed", "jobs", "object", "texture",
                                              "perturb"))
    runners["grasp"] = ExperimentRunner("grasp", "services.cli.commands:grasp_experiment",
                                        ("scenario", "placements", "seed", "jobs", "object", "perturb"))
    return runners


#: every experiment by name, in the order the command line lists them: its runner and its options
RUNNERS: dict[str, ExperimentRunner] = _runners()


def experiment_names() -> list[str]:
    return list(RUNNERS)


def options_taken(option: str) -> list[str]:
    """The experiments that take ``option`` (an argparse name)."""
    return [name for name, runner in RUNNERS.items() if option in runner.options]


def _copy(scenario: Scenario) -> Scenario:
    return msgspec.convert(msgspec.to_builtins(scenario), Scenario)


def default_scenario(experiment: "Experiment", arm: Optional[str] = None) -> Path:
    """An experiment's own start: its scenario file, or the one written for ``arm`` beside it
    (``<scenario>_<arm>.yaml``) where the shared one gives another arm's start."""
    shared = SCENARIOS / experiment.scenario
    own = SCENARIOS / f"{shared.stem}_{arm}.yaml"
    return own if arm is not None and own.is_file() else shared


@dataclass
class PlannedExperiment:
    """An experiment's runs, planned from its start: each spec with the scenario it runs."""

    name: str
    experiment: Experiment
    path: Path
    base: Scenario
    runs: list[tuple[RunSpec, Scenario]]


def plan_experiment(name: str, scenario_path: Optional[str | Path] = None, arm: Optional[str] = None
                    ) -> PlannedExperiment:
    """Experiment ``name``'s runs from its start (or ``scenario_path``'s start and goal) on ``arm`` (None: the
    scenario's). KeyError for an unknown experiment, ConfigError for a scenario that does not load."""
    if name not in EXPERIMENTS:
        raise KeyError(f"unknown experiment {name!r}; known: {', '.join(EXPERIMENTS)}")
    experiment = EXPERIMENTS[name]
    path = Path(scenario_path) if scenario_path is not None else default_scenario(experiment, arm)
    try:
        base = on_arm(load_scenario(path), arm, str(path))
    except ValueError as exc:
        raise ConfigError(str(path), str(exc)) from None
    base.clock = ClockMode.LOCKSTEP  # every experiment is a function of its scenario
    if not experiment.keep_law_options:
        base.law_options = {}
    runs = []
    for spec in experiment.runs:
        scenario = _copy(base)
        scenario.law, scenario.gains = spec.law, spec.gains
        scenario.law_options = {**scenario.law_options, **spec.options}
        runs.append((spec, scenario))
    return PlannedExperiment(name, experiment, path, base, runs)


def experiment_tasks(plan: PlannedExperiment, root: Path, profile: str, plots: bool, prefix: str = "",
                     processes: bool = False) -> list[RunTask]:
    """The plan's runs as tasks, each logging into ``root/<label>``, labelled ``prefix + label``."""
    return [RunTask(prefix + spec.label, scenario, root / spec.label, profile, plots, processes)
            for spec, scenario in plan.runs]


def finish_experiment(plan: PlannedExperiment, results: list[ServoResult], profile: str,
                      out_dir: Optional[Path]) -> dict:
    """The experiment's output from its runs' results (in the plan's order; their logs still on disk); with
    ``out_dir`` its comparison figures and report there."""
    experiment = plan.experiment
    rows: dict[str, dict] = {}
    trajectories: dict[str, list[dict]] = {}
    for (spec, scenario), result in zip(plan.runs, results):
        records = read_log(result.trajectory_log)
        trajectories[spec.label] = records
        rows[spec.label] = run_row(spec, result, records, scenario.robot.arm)
        if experiment.run_figures is not None:
            rows[spec.label].update(experiment.run_figures(scenario, result, records))
        rows[spec.label]["plots"] = result.plots if out_dir is not None else []
    output = {"experiment": plan.name, "seed": experiment.seed, "title": experiment.title,
              "paper": experiment.paper, "scenario": str(plan.path), "arm": plan.base.robot.arm, "profile": profile,
              "stack": results[0].stack if results else None, "runs": list(rows.values()),
              "summary": experiment.summarize(rows, trajectories), "report": None, "plots": [],
              # every run waited for every answer: the same numbers on a rerun (on this machine)
              "repeatable": all(row["lockstep_timeouts"] == 0 for row in rows.values())}
    if out_dir is not None:
        out = Path(out_dir)
        base = plan.base
        plots = comparison_plots(trajectories, out, title=experiment.title,
                                 threshold=base.convergence.rms, zone_distance=experiment.zone_distance,
                                 goal=base.goal.features, camera=base.camera)
        if experiment.figures is not None:
            plots += experiment.figures(trajectories, rows, out, base)
        output["plots"] = [str(p) for p in plots]
        write_results(output, out, report_markdown)
    return output


def run_plans(plans: list[PlannedExperiment], roots: list[Path], out_dirs: list[Optional[Path]], prefixes: list[str],
               profile: str, jobs: int, progress: Optional[Callable[[str, ServoResult], None]],
               on_iteration: Optional[Callable[[str, Scenario, object], None]], processes: bool = False) -> list[dict]:
    """Every plan's runs through one pool (``jobs`` at a time), plan ``i``'s logs under ``roots[i]``; each plan's
    output (:func:`finish_experiment`: its figures and report in ``out_dirs[i]``) made as soon as its last run
    ends, while the other plans' runs go on. The outputs in the plans' order."""
    tasks, owner = [], {}
    for i, (plan, root, prefix) in enumerate(zip(plans, roots, prefixes)):
        for k, task in enumerate(experiment_tasks(plan, root, profile, out_dirs[i] is not None, prefix=prefix,
                                                  processes=processes)):
            owner[id(task)] = (i, k)
            tasks.append(task)
    results: list[list[Optional[ServoResult]]] = [[None] * len(plan.runs) for plan in plans]
    outputs: list[Optional[dict]] = [None] * len(plans)

    def done(task: RunTask, result: ServoResult) -> None:
        i, k = owner[id(task)]
        results[i][k] = result
        if progress is not None:
            progress(task.label, result)
        if all(r is not None for r in results[i]):
            outputs[i] = finish_experiment(plans[i], results[i], profile, out_dirs[i])

    each = None if on_iteration is None else (lambda task, record: on_iteration(task.label, task.scenario, record))
    run_tasks(tasks, jobs, each, done)
    return outputs  # type: ignore[return-value]


def run_experiments(names: list[str], out_dir: Optional[str | Path] = None,
                    progress: Optional[Callable[[str, ServoResult], None]] = None, profile: str = "sim",
                    on_iteration: Optional[Callable[[str, Scenario, object], None]] = None,
                    jobs: int = 1, processes: bool = False) -> list[dict]:
    """Several experiments from their own starts, their runs side by side (``jobs`` at a time), each output in
    ``out_dir/<name>``; the outputs in the order of ``names``. Progress labels are ``<name> <run label>``."""
    plans = [plan_experiment(name) for name in names]
    with tempfile.TemporaryDirectory(prefix="mfvs-experiments-") as scratch:
        root = Path(out_dir) if out_dir is not None else Path(scratch)
        return run_plans(plans, [root / plan.name for plan in plans],
                          [None if out_dir is None else root / plan.name for plan in plans],
                          [f"{plan.name} " for plan in plans], profile, jobs, progress, on_iteration, processes)


def run_experiment(name: str, scenario_path: Optional[str | Path] = None, out_dir: Optional[str | Path] = None,
                   progress: Optional[Callable[[str, ServoResult], None]] = None, profile: str = "sim",
                   on_iteration: Optional[Callable[[str, Scenario, object], None]] = None,
                   arm: Optional[str] = None, jobs: int = 1, processes: bool = False) -> dict:
    """Run experiment ``name`` from its start (or ``scenario_path``'s start and goal) on ``arm`` (None: the
    scenario's), ``jobs`` runs at a time (:mod:`services.experiments.pool`: the same numbers as one at a time);
    ``progress(label, result)`` after each run, ``on_iteration(label, scenario, iteration_record)`` during it.
    Returns ``{"experiment", "title", "paper", "scenario", "arm", "runs": [...], "summary": {...}, "report",
    "plots"}``, the runs in the experiment's order."""
    plan = plan_experiment(name, scenario_path, arm)
    with tempfile.TemporaryDirectory(prefix=f"mfvs-{name}-") as scratch:
        root = Path(out_dir) if out_dir is not None else Path(scratch)
        return run_plans([plan], [root], [None if out_dir is None else Path(out_dir)], [""], profile, jobs,
                          progress, on_iteration, processes)[0]


