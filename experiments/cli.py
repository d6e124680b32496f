"""The commands' registry and their entry point: `python -m experiments <command> [options]` (`main`), and
`run_command`, one command run by another in this process. `python -m experiments --help` lists them."""
from __future__ import annotations

import argparse
import dataclasses
import importlib
import os
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from experiments import common

COMMANDS = {  # command -> (module, one-line help)
    "demo": ("experiments.demo", "the main job on one unseen episode: DP optimal and L1 plans, executed in C MuJoCo"),
    "check-model": ("experiments.diagnostics.check_model", "every model convention a scene file breaks "
                    "(your hand, your tool)"),
    "import-hand": ("experiments.diagnostics.import_hand", "a published MJCF hand (meshes, boxes, "
                    "servos) -> a hand file that follows the conventions"),
    "planners": ("experiments.diagnostics.planners", "every registered planner (yours too, with --plugin): "
                 "options, needs"),
    "surrogate": ("experiments.diagnostics.surrogate", "reward terms of a few meaningful grasps on one episode"),
    "bench-startup": ("experiments.bench.startup", "the Quickstart from a fresh process: first decision and DP table, "
                      "cache off / empty / on disk"),
    "bench-surrogate": ("experiments.bench.surrogate", "surrogate steps/s: vmapped vs one step at a time"),
    "bench-dp": ("experiments.bench.dp", "DP solve time: one episode, 27 batched, vs the step-at-a-time table"),
    "bench-search": ("experiments.bench.search", "the beam search beside the DP table: time an episode, IK problems, "
                     "plans equal to DP optimal's"),
    "bench-gym": ("experiments.bench.gym", "Gymnasium vector env steps/s: the native vmapped one vs SyncVectorEnv"),
    "dp": ("experiments.paper.dp", "exact DP (Bellman backups) over an episode set; grasp sequences and timeline"),
    "train": ("experiments.paper.train", "PPO on the training episodes, with or without DP pretraining, over seeds"),
    "train-curves": ("experiments.paper.train_curves", "Fig. 3: PPO training curves with and without DP pretraining"),
    "bench-ppo": ("experiments.bench.ppo", "PPO env steps/s and wall time to the DP-baseline return"),
    "physics": ("experiments.physics.check", "the physics check (MJX or C MuJoCo): a policy's grasp sequences, "
                "angle error under the torque; --compare: MJX against C"),
    "bench-physics": ("experiments.bench.physics", "the physics check against the engine alone, on 1, 2 and all cores"),
    "bench-scale": ("experiments.bench.scale", "physics episodes/s, DP tables/s and PPO steps/s "
                    "for 1, 2, 4 ... processes (one GPU and C cores each)"),
    "envelope": ("experiments.physics.envelope", "the stress envelope in physics: "
                 "falls classified by the oracle, regret"),
    "world-parts": ("experiments.physics.world_parts", "which part of the world gap drops the tool: falls in the "
                    "whole gap and in each of its fields alone"),
    "hands": ("experiments.physics.hands", "a hands x tools table: DP optimal, L1 and L1-physics on each model's "
              "variations in C MuJoCo, falls classified by the oracle"),
    "rescore": ("experiments.physics.rescore", "surrogate against physics: "
                "a recorded envelope pool scored under rewards (rho, AUC), no new physics"),
    "corpus": ("experiments.physics.corpus", "a physics corpus of the model: surrogate features of grasp sequences "
               "with what C MuJoCo did (shards, resumable)"),
    "calibrate": ("experiments.physics.calibrate", "the reward's weights and thresholds against physics "
                  "(train + val episodes); --learn: the learned physics term"),
    "fig4a": ("experiments.paper.fig4a", "Fig. 4a: surrogate returns relative to DP optimal, 95% CI, RM-ANOVA"),
    "fig4b": ("experiments.paper.fig4b", "Fig. 4b: the same policies closed loop in C MuJoCo (or MJX), "
              "angle error under the torque"),
    "table1": ("experiments.paper.table1", "Table 1: online wall-clock time per unseen episode, beside the paper's; "
               "--per-decision: latency per decision"),
    "ik-spikes": ("experiments.diagnostics.ik_spikes", "IK local minima: spikes between converged neighbours, "
                  "with and without extra starts"),
    "precision": ("experiments.diagnostics.precision", "float32 reward spread across CPUs, "
                  "1-ulp inputs and float64 (test tolerances)"),
    "reproduce": ("experiments.paper.reproduce", "everything above in sequence, one Markdown report (--quick on CPU)"),
    "figures": ("experiments.paper.figures", "every figure the README shows, each by its documented command and size; "
                "--stale: which records the code has moved past"),
}


AUTOTUNED = ("train", "bench-ppo", "bench-startup")  # commands that keep XLA's GPU autotuner (see
# deterministic_gpu_kernels); bench-startup's processes run as a user's own script does, with XLA's defaults


def deterministic_gpu_kernels(command: str | None) -> None:
    """Let XLA pick GPU kernels by its heuristics instead of timing candidates (`--xla_gpu_autotune_level=0`, unless
    XLA_FLAGS sets a level): the timed choice varies between runs, most under load, and with it the last bits of
    the policies' decisions; closed loop in physics such bits decide near-ties (Fig. 4b's marginal episodes:
    docs/lookahead.md). Training (`AUTOTUNED`) keeps the autotuner: the networks' GEMMs run much faster with it
    (docs/lookahead.md); its GPU runs can then differ between processes in the last bits. Must run before JAX
    starts."""
    flags = os.environ.get("XLA_FLAGS", "")
    if command not in AUTOTUNED and "xla_gpu_autotune_level" not in flags:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_gpu_autotune_level=0".strip()


def load_plugin(name: str) -> None:
    """Import a user's module by name (on sys.path, the working directory first) or from a .py file."""
    import importlib.util
    import pathlib

    path = pathlib.Path(name)
    try:
        if name.endswith(".py") or path.is_file():
            if not path.is_file():
                raise SystemExit(f"--plugin: no file {name!r}")
            spec = importlib.util.spec_from_file_location(path.stem, path)
            module = importlib.util.module_from_spec(spec)
            sys.modules[path.stem] = module
            spec.loader.exec_module(module)
        else:
            if "" not in sys.path and os.getcwd() not in sys.path:
                sys.path.insert(0, os.getcwd())
            importlib.import_module(name)
    except ModuleNotFoundError as e:
        raise SystemExit(f"--plugin: cannot import {name!r} ({e})") from None


def processes_asked(words: list[str]) -> tuple[int | None, list[str]]:
    """(N, the other words) of `--processes N` (or `--processes=N`) before the command; (None, words) without it."""
    cut = next((i for i, w in enumerate(words) if w in COMMANDS), len(words))
    for i, w in enumerate(words[:cut]):
        if w == "--processes" or w.startswith("--processes="):
            value = w.split("=", 1)[1] if "=" in w else (words[i + 1] if i + 1 < cut else "")
            rest = words[:i] + words[i + (1 if "=" in w else 2):]
            if not value.isdigit() or int(value) < 1:
                raise SystemExit(f"--processes: expects a number of processes >= 1, got {value!r}")
            return int(value), rest
    return None, list(words)


def main(argv: list[str] | None = None, outer: common.Run | None = None) -> common.Run:
    """`python -m experiments [--processes N] [--record] <command> [options]`: the command's module imported, its
    options parsed, its `Run` made (`make_run`; within `outer`, the run of the command that runs this one:
    `run_command`) and handed to its `main(args, run)`. Returns that run (where its results went)."""
    words = sys.argv[1:] if argv is None else argv
    n_processes, words = processes_asked(words)
    chosen = next((w for w in words if w in COMMANDS), None)  # only its module is imported (the others: help only)
    deterministic_gpu_kernels(chosen)
    from gsp_jax.core import distributed

    if n_processes is not None and n_processes > 1 and not distributed.requested():
        from experiments import processes

        processes.launch(n_processes, words)  # this command as N processes of one run (their coordinator: here)
        return
    distributed.initialize()  # one of several processes (ours, Slurm's, Open MPI's): JAX's runtime, before JAX runs
    import gsp_jax

    gsp_jax.enable_cache()  # XLA's compiled programs on disk (gsp_jax.core.cache; GSP_JAX_CACHE=off: none)

    parser = argparse.ArgumentParser(prog="python -m experiments", description=__doc__)
    parser.add_argument("--processes", type=int, default=None, metavar="N",  # read before parsing (processes_asked)
                        help="run the command as N processes of one run on this host (one GPU each where there are "
                             "GPUs, an equal share of the cores each); sweeps split their episodes between them "
                             "(docs/scale.md)")
    parser.add_argument("--record", action="store_true",
                        help="also write the result to docs/data/<name>_<device>.json and append it to "
                             "docs/data/history/")
    sub = parser.add_subparsers(dest="command", required=True)
    module = None
    for name, (path, help_) in COMMANDS.items():
        if name != chosen:
            sub.add_parser(name, help=help_.replace("%", "%%"))
            continue
        module = importlib.import_module(path)
        sp = sub.add_parser(name, help=help_.replace("%", "%%"), description=module.__doc__)
        module.add_arguments(sp)
        sp.add_argument("--plugin", action="append", default=[], metavar="MODULE",
                        help="import this module (a name on the path, or a .py file) first: its planners register "
                             "themselves (`gsp_jax.planners.registry.register`); repeatable")
        if name != "check-model":
            sp.add_argument("--model", default=None, metavar="NAME_OR_PATH",
                            help="the hand + tool scene: a shipped model (wrench, hammer, allegro, "
                                 "screwdriver) or a scene file "
                                 "(default: wrench); checked first (check-model)")
        if name not in ("check-model", "calibrate", "figures"):
            default = ("without it" if name in PAPER_BY_DEFAULT else
                       "the default where the model has weights, `calibrate --learn`")
            sp.add_argument("--learned", action="store_true",
                            help=f"plan with the learned physics term ({default}; refused where the model has "
                                 "none); results and records are named -learned")
            sp.add_argument("--paper", action="store_true",
                            help="plan with the paper's surrogate alone (no learned physics term)")
        if name in PHYSICS_COMMANDS:
            from gsp_jax.physics.config import CONTROLLERS

            sp.add_argument("--controller", choices=sorted(CONTROLLERS), default=None,
                            help="the contact controller in physics (default: measured, the contact frames the "
                                 "links have; paper: the paper's, its options' face normals, docs/physics.md); "
                                 "results and records are named -paper with it")
        if name in WORLD_COMMANDS:
            from gsp_jax.physics import world as world_lib

            sp.add_argument("--world", choices=list(world_lib.LEVELS), default=None,
                            help="the world the plans run in (default nominal: the planners' own model; gap: what "
                                 "a careful lab does not know of its hand and tool, wide: twice that; drawn per "
                                 "episode, hidden from every planner: docs/world.md); results and records are named "
                                 "-<level> with it")
            sp.add_argument("--world-seed", type=int, default=None, metavar="N",
                            help="the seed of the episodes' worlds (default 0)")
            sp.add_argument("--world-only", nargs="+", default=None, metavar="FIELD",
                            choices=[f.name for f in dataclasses.fields(world_lib.Gap)],
                            help="only these fields of the level's gap (the others as the model: which part of the "
                                 "gap drops the tool); results and records are named -<level>-<fields>")
    args = parser.parse_args(argv)
    for plugin in args.plugin:
        load_plugin(plugin)
    run = make_run(args, words, outer)
    from gsp_jax.core import files
    from gsp_jax.model import scenario

    try:
        for parts in getattr(module, "results_folders", lambda _: [])(args):  # its results folders, locked before
            run.results_dir(*parts)  # any set-up: a busy one stops it here (its own results_dir calls: no-ops)
        module.main(args, run)
    except (files.FolderInUse, scenario.EpisodeError) as e:  # a user's input or a busy folder: the message, no trace
        raise SystemExit(f"{args.command}: {e}") from None
    return run


def make_run(args: argparse.Namespace, words: list[str], outer: common.Run | None = None) -> common.Run:
    """The `Run` of a parsed command line: its `--model` loaded and checked (the outer run's model where it gives
    none; the default model for the outermost), the learned physics term (`_learned`: the model's where it has one,
    `--paper` / `--learned` to choose, the outer run's for a nested command), `--record` (or the outer run's), and
    the words its records name (the outer run's: the outermost command). `--model`, `--learned` and `--paper`
    leave `args`: a command reads them from its run."""
    from experiments import common
    from gsp_jax.model import load as model_lib
    from gsp_jax.surrogate import learned

    outer = outer or common.Run()
    model = outer.model  # check-model takes no --model: the outer run's (None: the default model)
    if "model" in args:
        given = args.model is not None
        try:
            model = model_lib.load_model(args.model if given else outer.model)
        except model_lib.ModelError as e:
            raise SystemExit(f"--model: {e}") from None
        if given:
            print(f"model: {model.name} ({model.path})", flush=True)
    use_learned = _learned(args, model, outer)  # `Surrogate(run.model, learned=)`
    if use_learned and "model" in args and not outer.learned:
        print(f"learned physics term: {learned.path_of(model)}" + (
            "" if getattr(args, "learned", False) else " (the model's default; --paper: the paper's surrogate)"),
            flush=True)
    controller = getattr(args, "controller", None) or outer.controller
    world = getattr(args, "world", None) or outer.world
    world_seed = outer.world_seed if getattr(args, "world_seed", None) is None else args.world_seed
    world_only = tuple(getattr(args, "world_only", None) or outer.world_only)
    if world_only and world == "nominal":
        raise SystemExit(f"--world-only {' '.join(world_only)}: a part of a gap needs --world gap or wide")
    for name in ("model", "learned", "paper", "controller", "world", "world_seed", "world_only"):
        vars(args).pop(name, None)
    return common.Run(model=model, learned=use_learned, record=outer.record or args.record,
                      command=outer.command or tuple(words), controller=controller, world=world,
                      world_seed=world_seed, world_only=world_only)


PHYSICS_COMMANDS = ("demo", "physics", "bench-physics", "bench-scale", "envelope", "hands", "corpus", "calibrate",
                    "fig4b", "table1", "reproduce", "world-parts")  # they simulate: `--controller` chooses the contact
# controller
# they take `--world`: plans run in a world unlike the model (corpus, calibrate --learn: a term's runs do)
WORLD_COMMANDS = ("physics", "envelope", "fig4b", "corpus", "calibrate")


PAPER_BY_DEFAULT = ("corpus", "reproduce")  # the learned term's own data (its corpus plans with the analytic
# surrogate), and the paper's reproduction: these plan without the term unless --learned


def _learned(args: argparse.Namespace, model, outer) -> bool:
    """Whether a command plans with the learned physics term: `--paper` no, `--learned` yes (the model's weights
    checked before any work); else a nested command as the command that runs it (for another model than its own:
    that model's term where it has one), and a command that plans (it takes --learned) with the model's weights
    where the model has them (`learned.has_own`), except `PAPER_BY_DEFAULT`."""
    from gsp_jax.surrogate import learned

    paper, asked = getattr(args, "paper", False), getattr(args, "learned", False)
    if paper and asked:
        raise SystemExit("--learned and --paper: one or the other")
    if paper:
        return False
    if outer.command and outer.learned and not asked and "model" in args and model is not outer.model:
        return learned.has_own(model)  # a nested command for another model: that model's term where it has one
    if asked or outer.learned:
        if "model" in args:
            try:
                learned.resolve(True, model)
            except learned.LearnedTermError as e:
                raise SystemExit(f"--learned: {e}") from None
        return True
    if outer.command or "learned" not in args or args.command in PAPER_BY_DEFAULT:
        return False
    return learned.has_own(model)


def run_command(words: list[str], run: common.Run) -> common.Run:
    """Run another command in this process, as `python -m experiments <words>` would, within `run` (the running
    command's: its model, learned term and --record, where the words give none; its records name `run.command`): how
    a pipeline such as `reproduce` composes commands, reading their results from their files (the returned run's
    `results_dir`)."""
    return main(list(words), run)
