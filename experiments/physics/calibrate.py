"""`python -m experiments calibrate [--sets train,val] [--random 16] [--backend c] [--write]`: the surrogate's reward
calibrated against the physics check, on the training and validation episodes only (never the evaluation set).

1. Every candidate `RewardConfig` of a grid (the wrench solves' grip, fixed or in proportion to the tool's mass, the
   fall threshold, the grasp-change term on or off) scores every episode's DP table. The IK is shared by all
   candidates (it does not depend on the reward), the wrench solves by all candidates of one grip.
2. A pool of grasp sequences per episode: each candidate's DP optimal and DP baseline (the nominal episode's
   optimal sequence), `--random` random sequences feasible under the candidates' tables in turn (holding the grasp
   with probability 0, 0.6 or 0.9), and the scripted references of `physics` (four tips, the alternating changes,
   add-and-slide, one tip). Duplicates are simulated once.
3. The pool through the physics check (`--backend c`: C MuJoCo on the CPU, the same controller as MJX), open loop.
   Outcomes are cached in results/calibrate/physics_<backend>.json, so an interrupted run resumes.
4. Per candidate: the Spearman rank correlation between each sequence's surrogate return and its simulated
   -angle error (180 deg when the tool fell), pooled; the share of surrogate-feasible sequences that hold; DP
   optimal's falls and grasp changes. The winner: the candidate whose DP-optimal plans fall least in physics, then
   the higher correlation. (A planner uses the surrogate through its optimum: correlation alone can pick a reward
   whose DP plans drop the tool far more often; docs/calibration.md.)

Prints the sweep as a table; writes results/calibrate/sweep.json, and with --write the winner into
models/reward_calibration.json (`reward.write_calibration`), where `RewardConfig` reads its defaults.

`calibrate --learn [--shards 40] [--world gap]`: instead, the model's learned physics term, from corpus to weights
(`learn`); with `--world` its corpus runs in worlds drawn from that gap (results/corpus-gap/: docs/world.md).

`calibrate --tune [--model M] [--set stress-cal] [--write]`: instead, the contact controller's settings that stay
tuned (`tuning.TUNABLE`: the preferred grip, the rotational damping's bound, the pose loop's frequency) for the model,
on episodes never used to test it (`controller_tuning`); with --write into `<scene stem>.controller.json` beside the
scene, which every command then uses for that model (and refuses for another)."""
from __future__ import annotations

import argparse
import itertools
import pathlib
import time

import jax
import numpy as np

from experiments import cli
from experiments.common import RESULTS, Run, table
from gsp_jax.planners import registry as gsp_planners
from gsp_jax.model import load as model_lib
from gsp_jax.physics import tuning
from gsp_jax.planning import evaluation
from gsp_jax.core import files, stats
from gsp_jax.model import grasps, scenario
from gsp_jax.surrogate import learned, reward
from gsp_jax import physics
from gsp_jax.physics import calibration, corpus
from gsp_jax.physics.calibration import candidate_tables, candidates, pool_key, score_candidates, sequence_pool
from gsp_jax.core.stats import cluster_bootstrap_se

CALIBRATION_JSON = reward.CALIBRATION_JSON  # where `--write` puts the chosen defaults


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--sets", default="train,val", help="comma-separated episode sets (never eval)")
    p.add_argument("--random", type=int, default=16, help="random feasible sequences per episode")
    p.add_argument("--backend", default="c", choices=physics.BACKENDS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--chunk", type=int, default=512, help="most sequences per physics batch")
    p.add_argument("--write", action="store_true", help="write the winner into models/reward_calibration.json")
    p.add_argument("--from-sweep", default=None, help="choose from a saved results/calibrate/sweep.json (no reruns)")
    p.add_argument("--tune", action="store_true",
                   help="instead: tune the contact controller for the model (`controller_tuning`, below)")
    p.add_argument("--set", default="stress-cal", help="with --tune: the episodes it tunes on (not eval or "
                                                         "stress: they test it)")
    p.add_argument("--subset", type=int, default=0, help="with --tune: this many episodes of the set, spread evenly "
                                                          "(0: all)")
    p.add_argument("--grid", default="grip_force=4,8,12;rotation_step=0.3,1;tool_freq=10,15",
                   help="with --tune: the candidates, NAME=v,v,...;... (every combination)")
    p.add_argument("--learn", action="store_true",
                   help="instead: the model's learned physics term, corpus to weights (`learn`, below)")
    p.add_argument("--shards", type=int, default=40, help="with --learn: corpus shards to hold (0: fit on the corpus "
                                                          "as it is)")
    p.add_argument("--episodes", type=int, default=64, help="with --learn: episodes a corpus shard")
    p.add_argument("--corpus", nargs="+", default=None, metavar="FOLDER",
                   help="with --learn: the corpus folders (default: results/corpus[-<model>], and "
                        "results/corpus-learned[-...] where `corpus --learned` made one)")
    p.add_argument("--out", default=None, help="with --learn: where the weights go (default: beside the scene)")
    p.add_argument("--keep", action="store_true",
                   help="with --learn: install the term beside the scene even where, on the test split, it ranks "
                        "hold against fall no better than the analytic return (by default it is then kept aside)")
    p.add_argument("--fit-seed", type=int, default=0, help="with --learn: the split's and the network's seed")
    p.add_argument("--epochs", type=int, default=learned.FitConfig.epochs, help="with --learn: at most")
    p.add_argument("--members", type=int, default=learned.FitConfig.members,
                   help="with --learn: networks in the hazard's ensemble")


def _from_sweep(path: str, write: bool, folder: pathlib.Path) -> None:
    """`--from-sweep`: choose (and with `write`, write) from a saved sweep (its physics cache read from `folder`,
    results/calibrate)."""
    summary = files.read_json(path)
    if "rows" not in summary:
        summary["rows"] = [[r["label"], r["spearman"], r["feasible"], r["feasible_held"], r["dp_opt_falls"],
                            r["dp_opt_angle"], r["dp_opt_changes"]] for r in summary["sweep"]]
    summary.setdefault("best_spearman_label", max(summary["sweep"], key=lambda r: np.nan_to_num(
        r["spearman"], nan=-1.0))["label"])
    cache_path = folder / f"physics_{summary['backend']}.json"
    if cache_path.exists():  # sweeps written before the per-episode falls were kept: read them off the cache
        cache = files.reuse_json(cache_path, lambda c: isinstance(c, dict)) or {}
        names = summary["episodes"]
        for r in summary["sweep"]:
            if "dp_opt_fell" in r or "dp_opt_sequences" not in r:
                continue
            keys = [pool_key(names, e, r["dp_opt_sequences"][n]) for e, n in enumerate(names)]
            if all(k in cache for k in keys):
                r["dp_opt_fell"] = [bool(cache[k][1]) for k in keys]
    choose_and_write(summary, write)


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    if getattr(args, "tune", False):
        return [("calibrate-controller",)]
    return [("learn",), *([] if args.corpus else [("corpus",)])] if args.learn else [("calibrate",)]


def main(args: argparse.Namespace, run: Run) -> None:
    if run.gap is not None and not getattr(args, "learn", False):
        raise SystemExit(f"calibrate: --world {run.world_name} is for --learn (a learned term from a corpus run in "
                         "that world); the controller and the wrench are calibrated in the model itself")
    if getattr(args, "tune", False):
        if args.learn:
            raise SystemExit("calibrate: --tune and --learn are two runs; give one")
        return controller_tuning(args, run)
    if getattr(args, "learn", False):
        return learn(args, run)
    if args.from_sweep:
        return _from_sweep(args.from_sweep, args.write, run.results_dir("calibrate"))
    sets = [s.strip() for s in args.sets.split(",") if s.strip()]
    if any(s.startswith("eval") or s == "all" for s in sets):
        raise SystemExit(f"--sets: calibration never uses the evaluation episodes, got {args.sets!r}")
    episodes = {}
    for s in sets:
        episodes.update(scenario.episode_set(s, run.model))
    names, batch = list(episodes), scenario.stack(list(episodes.values()))
    configs = candidates()
    t0 = time.perf_counter()
    print(f"calibrate: {len(configs)} candidate rewards x {len(names)} episodes ({'+'.join(sets)}) ...", flush=True)
    tables = candidate_tables(configs, batch, run.model)
    nominal_tables = candidate_tables(configs, scenario.stack([scenario.make_episode(model=run.model)]), run.model)
    print(f"  tables: {time.perf_counter() - t0:.0f} s", flush=True)
    pool = sequence_pool(configs, tables, nominal_tables, batch, args.random, args.seed, run.model)
    cache = calibration.simulate_pool(pool, episodes, args.backend, args.chunk,
                                      run.results_dir("calibrate") / f"physics_{args.backend}.json", t0, run.model)
    flat = [(e, kind, seq) for e in range(len(names)) for kind, seq in pool[e]]
    angle = np.array([cache[pool_key(names, e, seq)][0] for e, _, seq in flat])
    fell = np.array([cache[pool_key(names, e, seq)][1] for e, _, seq in flat])
    results, rets = score_candidates(configs, tables, batch, names, flat, angle, fell)
    rho_all = np.nan_to_num(np.array([r["spearman"] for r in results]), nan=-1.0)
    top = int(np.argmax(rho_all))
    se = cluster_bootstrap_se(rets[top], -angle, np.array([e for e, _, _ in flat]), args.seed)
    summary = dict(sets=sets, episodes=names, sequences=len(flat), physics_falls=int(fell.sum()),
                   best_spearman=float(rho_all[top]), best_spearman_se=se, best_spearman_label=results[top]["label"],
                   backend=args.backend, chosen=None, sweep=results,
                   kinds={k: int(sum(1 for _, kk, _ in flat if kk == k)) for k in sorted({k for _, k, _ in flat})},
                   wall_s=time.perf_counter() - t0,
                   rows=[[r["label"], r["spearman"], r["feasible"], r["feasible_held"], r["dp_opt_falls"],
                          r["dp_opt_angle"], r["dp_opt_changes"]] for r in results])
    print(f"\n{len(flat)} sequences on {len(names)} episodes ({'+'.join(sets)}), {int(fell.sum())} fell in physics "
          f"({args.backend}); {time.perf_counter() - t0:.0f} s")
    choose_and_write(summary, args.write)  # sets summary["chosen"]
    files.write_json(run.results_dir("calibrate") / "sweep.json", summary)


def choose_and_write(summary: dict, write: bool) -> dict:
    """Print the sweep, pick the winner (`calibration.choose`) and, with `write`, write it."""
    results, n_e = summary["sweep"], len(summary["episodes"])
    print(table(["candidate reward", "rho", "feasible", "of them held", f"DP opt falls /{n_e}", "DP opt angle",
                 "DP opt changes"], summary["rows"], ".3f"))
    verdict = calibration.choose(results, calibration.label(reward.RewardConfig()))
    challenger, incumbent, chosen = verdict["challenger"], verdict["incumbent"], verdict["chosen"]
    print(f"\nhighest rho: {summary['best_spearman_label']} ({summary['best_spearman']:.3f} +- "
          f"{summary['best_spearman_se']:.3f}, bootstrap over episodes)")
    print(f"challenger (fewest DP-optimal falls, then rho): {challenger['label']} (rho {challenger['spearman']:.3f}, "
          f"DP optimal falls {challenger['dp_opt_falls']}/{n_e}, {challenger['dp_opt_changes']:.2f} grasp changes)")
    if verdict["challenge"] is not None:
        summary["challenge"] = c = verdict["challenge"]
        print(f"against the incumbent {incumbent['label']} (DP optimal falls {incumbent['dp_opt_falls']}/{n_e}): "
              f"the challenger alone holds {c['held_only_by'][0]} episodes, the incumbent alone "
              f"{c['held_only_by'][1]}; sign test p = {c['p']:.3f}")
    summary["chosen"] = chosen
    print(f"chosen: {chosen['label']}")
    if write:
        write_calibration(chosen, summary)
        print(f"wrote {CALIBRATION_JSON}")
    return chosen


def write_calibration(res: dict, summary: dict) -> None:
    """The chosen sweep row `res` and what the sweep measured for it, written to `CALIBRATION_JSON`."""
    cfg, default = res["config"], reward.RewardConfig()
    values = {k: cfg.get(k, getattr(default, k)) for k in reward.CALIBRATED_FIELDS}
    reward.write_calibration(CALIBRATION_JSON, values, calibration.measured(res, summary))


# ---------------------------------------------------------------------------------------- --learn
# `calibrate --learn`: the model's learned physics term, from corpus to weights.
#
# 1. The model's physics corpus (the `corpus` command: results/corpus[-<model>]/, or `--corpus`) extended to
#    `--shards` shards; a corpus already there is reused (`--shards 0`: fit on what it holds).
# 2. The hazard (`gsp_jax.surrogate.learned.fit`) on the transitions a planner can meet (`learned.surrogate_alive`)
# that physics
#    reached, split by episode into train / validation / test, early stopping on validation.
# 3. Checks on the test episodes, never used in fitting: AUC of the run's predicted chance to hold, and of its
#    return with and without the term (`learned.returns`), for hold against fall; the share of the sequences the
#    surrogate calls feasible that hold, with and without; calibration per probability bin (`learned.reliability`);
#    the hazard's AUC per sequence kind.
# 4. The weights beside the model's scene (`learned.path_of`, or `--out`), where `Surrogate(learned=True)` and
#    `--learned` find them, if on the test split the return with the term ranks hold against fall at least as well
#    as without it (the planner that holds is the default, not a term that misjudges; `--keep`: installed anyway);
#    otherwise in results/learn[-<model>]/rejected.learned.npz. Writes results/learn[-<model>]/report.json; prints
#    the checks as a table last.


def _checks(data: dict, fitted: learned.Fitted, cfg: reward.RewardConfig) -> dict:
    """The test split's figures (see the module's docstring)."""
    test = np.isin(data["episode"], fitted.split["test"])
    x, fell = data["features"][test], data["fell"][test]
    p = np.asarray(jax.jit(learned.hazard)(fitted, x))  # (M, T)
    met = learned.surrogate_alive(x)
    meet = data["alive"][test] & met
    hold_p = np.prod(np.where(met, 1 - p, 1.0), 1)  # the chance to hold through
    plain, plain_ok = learned.returns(x, None, cfg)
    risky, risky_ok = learned.returns(x, p, cfg)
    kinds = data["kinds"][data["kind"][test]]
    out = dict(test_runs=int(test.sum()), test_episodes=len(fitted.split["test"]), test_falls=int(fell.sum()),
               auc_hold_chance=stats.auc(hold_p[~fell], hold_p[fell]),
               auc_return_analytic=stats.auc(plain[~fell], plain[fell]),
               auc_return_learned=stats.auc(risky[~fell], risky[fell]),
               feasible_analytic=int(plain_ok.sum()), feasible_hold_analytic=float(np.mean(~fell[plain_ok])),
               feasible_learned=int(risky_ok.sum()),
               feasible_hold_learned=float(np.mean(~fell[risky_ok])) if risky_ok.any() else float("nan"),
               transition_auc=stats.auc(p[meet & data["fell_here"][test]], p[meet & ~data["fell_here"][test]]),
               reliability=learned.reliability(p[meet], data["fell_here"][test][meet]))
    ep = data["episode"][test]
    out["pool_regret_analytic"], out["pool_regret_learned"], out["pool_holdable"] = (
        *(_pool_regret(score, fell, ep) for score in (plain, risky)), int(sum(not fell[ep == e].all()
                                                                            for e in np.unique(ep))))
    base = np.array([k.rstrip("0123456789") for k in kinds])
    out["per_kind"] = {k: dict(runs=int(np.sum(of)), falls=int(fell[of].sum()),
                               auc=stats.auc(hold_p[of & ~fell], hold_p[of & fell]))
                       for k in sorted(set(base)) for of in [base == k]}
    return out


def installs(checks: dict) -> bool:
    """Whether a fitted term becomes its model's default: on the test split, the return with it ranks hold against
    fall at least as well as the analytic return (AUC; not where either is undefined: a split without a hold or
    without a fall says nothing)."""
    return bool(checks["auc_return_learned"] >= checks["auc_return_analytic"])


def learn(args: argparse.Namespace, run: Run) -> None:
    """`--learn`: the model's learned physics term, corpus to weights (see the section's comment)."""
    model = run.model
    t0 = time.perf_counter()
    folders = [pathlib.Path(f) for f in args.corpus] if args.corpus else [run.results_dir("corpus")]
    if args.shards:  # the corpus command extends it (it prints its progress and counts)
        cli.run_command(["corpus", "--folder", str(folders[0]), "--shards", str(args.shards), "--episodes",
                         str(args.episodes)], run)
    if args.corpus is None:  # the learned planners' sequences, where `corpus --learned` made them
        on_policy = folders[0].with_name(folders[0].name + "-learned")
        folders += [on_policy] if (on_policy / "manifest.json").exists() else []
    stores = [_store(f, model, run.physics_config(), run.gap) for f in folders]
    data = _joined([s.load() for s in stores])
    t_corpus = time.perf_counter() - t0
    space = grasps.space_of(model.hand)
    data["features"] = np.asarray(learned.inputs(data["features"], data["grasps"], space))  # the network's inputs
    meet = data["alive"] & learned.surrogate_alive(data["features"])
    print(f"learn: {len(data['fell'])} runs, {int(meet.sum())} transitions a planner meets, "
          f"{int(data['fell'].sum())} falls; fitting ...", flush=True)
    config = learned.FitConfig(epochs=args.epochs, members=args.members)
    fitted = learned.fit(data["features"], data["fell_here"], meet, data["episode"],
                         jax.random.PRNGKey(args.fit_seed), model.digest, learned.input_names(space), config,
                         progress=True)
    t_fit = time.perf_counter() - t0 - t_corpus
    cfg = reward.RewardConfig()
    checks = _checks(data, fitted, cfg)
    out = pathlib.Path(args.out) if args.out else learned.path_of(model)
    if not (installs(checks) or args.out or args.keep):  # not the model's default: every command would plan with it
        out = run.results_dir("learn") / "rejected.learned.npz"
        print(f"learn: NOT installed beside the scene: on the test split the return with the term ranks hold against "
              f"fall no better than without it (AUC {checks['auc_return_learned']:.3f} against "
              f"{checks['auc_return_analytic']:.3f}; {checks['test_runs']} runs, {checks['test_falls']} falls), so "
              f"the commands keep planning without it. More of the corpus gives it more to learn from (--shards N); "
              f"--keep installs it anyway. Weights kept in {out}", flush=True)
    learned.save(fitted, out)
    report = dict(model=model.name, digest=model.digest, weights=str(out), corpus=[str(s.folder) for s in stores],
                  shards=sum(len(s.manifest["shards"]) for s in stores), runs=int(len(data["fell"])),
                  physics=stores[0].manifest["physics"],
                  epochs=len(fitted.history),
                  corpus_s=t_corpus, fit_s=t_fit, risk_falls=cfg.risk_falls, **checks)
    files.write_json(run.results_dir("learn") / "report.json", report)
    print(f"learn: weights in {out}; report in {run.results_dir('learn') / 'report.json'}", flush=True)
    print(table(["reliability bin", "transitions", "predicted", "observed"],
                [[f"{b['low']:.1f}-{b['high']:.1f}", b["n"], b["predicted"], b["observed"]]
                 for b in checks["reliability"] if b["n"]]))
    rows = [["test runs (episodes)", f"{checks['test_runs']} ({checks['test_episodes']})"],
            ["falls", checks["test_falls"]],
            ["AUC, predicted chance to hold", checks["auc_hold_chance"]],
            ["AUC, return: analytic", checks["auc_return_analytic"]],
            ["AUC, return: with the term", checks["auc_return_learned"]],
            ["feasible that hold: analytic", f"{100 * checks['feasible_hold_analytic']:.1f}% of "
                                              f"{checks['feasible_analytic']}"],
            ["feasible that hold: with the term", f"{100 * checks['feasible_hold_learned']:.1f}% of "
                                                   f"{checks['feasible_learned']}"],
            ["AUC per transition", checks["transition_auc"]],
            ["best of the episode's runs fell, another held: analytic return",
             f"{checks['pool_regret_analytic']} of {checks['pool_holdable']}"],
            ["the same: return with the term", f"{checks['pool_regret_learned']} of {checks['pool_holdable']}"],
            ["corpus, fit [s]", f"{t_corpus:.0f}, {t_fit:.0f}"]]
    run.record_figures("learned_term", {k: v for k, v in report.items() if k not in ("reliability",)})
    print(table([f"learned physics term, {model.name}", "test split"], rows))


def parse_grid(text: str) -> list[dict]:
    """`--grid` "NAME=v,v;NAME=v" as every combination of the values, in order: [{NAME: v, ...}, ...].
    SystemExit naming the part that is not a tunable field with positive numbers."""
    axes = []
    for part in (p.strip() for p in text.split(";") if p.strip()):
        name, _, values = part.partition("=")
        name = name.strip()
        if name not in tuning.TUNABLE:
            raise SystemExit(f"--grid: {name!r} is not a tunable controller field (tunable: "
                             f"{', '.join(tuning.TUNABLE)})")
        try:
            vals = [float(v) for v in values.split(",") if v.strip()]
        except ValueError:
            raise SystemExit(f"--grid: {part!r}: the values must be numbers, NAME=v,v,...") from None
        if not vals or not all(np.isfinite(v) and v > 0 for v in vals):
            raise SystemExit(f"--grid: {part!r}: give one or more finite values > 0")
        axes.append((name, vals))
    if not axes:
        raise SystemExit(f"--grid: no candidates in {text!r} (NAME=v,v,...;...)")
    return [dict(zip([n for n, _ in axes], combo)) for combo in itertools.product(*[v for _, v in axes])]


def controller_tuning(args: argparse.Namespace, run: Run) -> None:
    """`--tune`: every candidate of `--grid` (the model's controller now, `tuning.config`, with those fields; the
    settings now join the grid where it lacks them) runs the model's DP optimal and DP baseline plans, closed loop
    in C MuJoCo, on the `--set` episodes (the stress set's calibration slice by default: disjoint from the stress,
    evaluation and variations sets that test the result). The best is the candidate with the fewest falls, then the
    lower mean held angle; it is chosen over the settings now only where it holds significantly more of the same
    runs (McNemar's sign: held more minus held less > 2 sqrt of their sum), else the settings stay. With --write
    the choice goes beside the scene (`tuning.save`), where every command on that model reads it."""
    if args.set.startswith("eval") or args.set in ("stress", "variations", "all"):
        raise SystemExit(f"calibrate --tune: --set {args.set!r} tests the controller; tune on another set "
                         f"(stress-cal, train or val)")
    if run.controller == "paper":
        raise SystemExit("calibrate --tune: the paper's controller is never tuned (drop --controller paper)")
    grid = parse_grid(args.grid)
    model = run.model or model_lib.load_model(None)
    current = tuning.config(model, run.controller)
    now = {k: current.value(k) for k in grid[0]}  # the model's settings now, on the grid's fields
    grid = grid if now in grid else [now, *grid]
    if args.subset < 0:
        raise SystemExit(f"calibrate --tune: --subset must be >= 0, got {args.subset}")
    ctx = evaluation.context(args.set, args.subset or None, model=model, results=RESULTS, learned=run.learned,
                             rl=False)
    kinds = ("dp-opt", "dp-base")
    groups = [gsp_planners.make(ctx, k) for k in kinds]
    t0 = time.perf_counter()
    print(f"calibrate --tune: {len(grid)} candidates x {len(ctx.names)} episodes ({args.set}) x "
          f"{len(kinds)} planners in C MuJoCo, model {model.label}; now {tuning.load(model) or 'untuned'}",
          flush=True)
    rows, out, fells = [], [], []
    for i, fields in enumerate(grid):
        phys = physics.Physics(ctx.surrogate, current.replace(**fields))
        res = phys.simulate_many(groups, ctx.batch, backend="c")
        fell = np.stack([np.asarray(r.fell) for r in res])  # (planners, N)
        angle = np.stack([np.asarray(r.angle_error) for r in res])
        held = angle[~fell]
        fells.append(fell.reshape(-1))
        out.append(dict(fields=fields, falls=int(fell.sum()), falls_by_planner=dict(zip(kinds, fell.sum(1).tolist())),
                        mean_angle_held_deg=float(held.mean()) if held.size else float("nan")))
        print(f"  [{i + 1}/{len(grid)}] {fields}: {out[-1]['falls']} falls of {fell.size}, held angle "
              f"{out[-1]['mean_angle_held_deg']:.2f} deg ({time.perf_counter() - t0:.0f} s)", flush=True)
        rows.append([", ".join(f"{k}={v:g}" for k, v in fields.items()), *fell.sum(1).tolist(), out[-1]["falls"],
                     out[-1]["mean_angle_held_deg"]])
    best = min(range(len(out)), key=lambda j: (out[j]["falls"], np.nan_to_num(out[j]["mean_angle_held_deg"], nan=1e9)))
    base = grid.index(now)
    gained, lost = int(np.sum(fells[base] & ~fells[best])), int(np.sum(~fells[base] & fells[best]))
    significant = gained - lost > 2 * np.sqrt(gained + lost)  # McNemar's sign, ~2 sigma: not a draw's noise
    chosen = out[best if significant else base]["fields"]
    summary = dict(model=model.name, digest=model.digest, set=args.set, episodes=len(ctx.names), planners=kinds,
                   controller=run.controller, candidates=out, best=out[best]["fields"], chosen=chosen, before=now,
                   held_more=gained, held_less=lost, significant=bool(significant), wall_s=time.perf_counter() - t0)
    files.write_json(run.results_dir("calibrate-controller") / "sweep.json", summary)
    if args.write:
        path = tuning.save(model, chosen, dict(set=args.set, episodes=len(ctx.names), planners=list(kinds),
                                               candidates=out), run.controller)
        print(f"calibrate --tune: wrote {path} (every command on {model.name} now uses it)", flush=True)
    else:
        print("calibrate --tune: not written (--write puts the winner beside the scene)", flush=True)
    print(table(["candidate", *kinds, "falls", "held angle [deg]"], rows))
    verdict = (f"it holds {gained} runs the model's settings now drop and drops {lost} they hold: "
               f"{'more than' if significant else 'within'} 2 sigma of a draw")
    print(f"fewest falls: {', '.join(f'{k}={v:g}' for k, v in out[best]['fields'].items())} ({out[best]['falls']} "
          f"falls; now {out[base]['falls']}); {verdict}; chosen: "
          f"{', '.join(f'{k}={v:g}' for k, v in chosen.items())}")


def _pool_regret(score: np.ndarray, fell: np.ndarray, episode: np.ndarray) -> int:
    """Episodes where the run of the highest score fell while another run of the episode held: a planner's regret
    when it chooses among the corpus's sequences by `score`."""
    return int(sum(fell[s][np.argmax(score[s])] for e in np.unique(episode)
                   if not fell[s := episode == e].all()))


def _joined(parts: list[dict]) -> dict:
    """Corpora's arrays as one (episode ids renumbered past the earlier corpora's)."""
    offset, out = 0, []
    for part in parts:
        out.append(dict(part, episode=part["episode"] + offset))
        offset += len(part["episode_names"])
    return {k: np.concatenate([p[k] for p in out]) for k in out[0]}


def _store(folder: pathlib.Path, model, config, gap=None) -> corpus.Store:
    """The corpus in `folder`, of `model` and run with the physics settings `config` in worlds of `gap` (None: the
    nominal model; the term learns what that controller drops there), else SystemExit saying why."""
    if not (folder / "manifest.json").exists():
        raise SystemExit(f"calibrate --learn: {folder} holds no corpus (`python -m experiments corpus` makes one; "
                         "--shards N > 0 here too)")
    try:
        store = corpus.Store.open(folder, model)
        corpus.check_physics(store, config, gap)
    except corpus.CorpusError as e:
        raise SystemExit(f"calibrate --learn: {e}") from None
    return store
