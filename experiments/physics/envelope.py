"""`python -m experiments envelope --set stress|eval [--random 8]`: do the plans hold where holding is possible?

Every episode of the set runs in C MuJoCo under the constant four-tip grasp, DP optimal, L1, L2 and RL (closed
loop), and a pool of `--random` random surrogate-feasible grasp sequences (half of them keeping each grasp with
probability 0.8), in chunks of `--chunk` episodes, each one lockstep (`Physics.simulate_many`). Each finished chunk's
outcomes are kept at once in results/envelope/<set>.parts/, named by a hash of what they depend on (`parts_key`): a
run that stops part-way says where in one line and leaves them, and the same command runs again only the rest.

Every fall is classified by the feasibility oracle (`gsp_jax.physics.oracle`) on the grasps the run held:
*necessary* (at some point no forces in the friction cones hold the tool within the motors' limits), *controller*
(forces exist everywhere: the controller let it fall) or *undetermined* (the cone's outer and inner pyramids
disagree). Beside it the oracle is asked at the configurations the run *reached* (`Oracle.simulated`, the simulated
joint angles and tool pose before each decision and at the hold's start, up to the fall): a necessary fall *before*
the point the oracle calls impossible is counted as `early` (the controller dropped the tool before the grasp became
impossible to hold). A planner's *regret* counts the episodes where it fell while some other sequence of the pool
(the four tips, another planner, a random one) held.

On the pool the surrogate is judged as a predictor of physics: the share of the sequences it calls feasible that
hold, and how well its return separates holds from falls (AUC, pooled and within episodes) and ranks the angle
errors (Spearman). Writes results/envelope/<set>.json; prints the table last.
"""
from __future__ import annotations

import argparse
import hashlib
import pathlib
import sys
import time
import warnings
import zipfile

import jax
import jax.numpy as jnp
import numpy as np

from experiments import common
from experiments.common import Run, table
from gsp_jax.core import distributed, files
from gsp_jax.planning import dp, evaluation, policies, rollout
from gsp_jax import physics
from gsp_jax.model import scenario
from gsp_jax.physics import c_backend
from gsp_jax.physics import world as world_lib
from gsp_jax.physics.envelope import PREDICTED_HOLD, classify, summarise
from gsp_jax.planners import registry as gsp_planners

PLANNERS = ("four-tips", "dp-opt", "L1", "L2", "rl")
CHUNK = 30  # episodes per lockstep by default: the stress set's 120 run as 4 chunks, each kept when it finishes
FIELDS = ("fell", "angle_error", "actions", "grasps", "fall_time", "reached")  # a chunk's kept outcomes (`outcomes`)


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--set", default="stress", choices=["stress", "stress-cal", "eval", "val", "train", "variations"])
    p.add_argument("--episodes", type=int, default=None, help="only N episodes, spread over the set")
    p.add_argument("--random", type=int, default=8, help="random surrogate-feasible sequences per episode")
    p.add_argument("--policies", nargs="+", default=list(PLANNERS), metavar="NAME",
                   help=f"registered planners to run (default: {' '.join(PLANNERS)}; rl only where the model has a "
                        "PPO policy); --plugin adds yours")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--policy-dir", default=None)
    p.add_argument("--jobs", type=int, default=None, help="processes classifying falls (default: the CPU cores)")
    p.add_argument("--physics-lookahead", type=int, default=0, metavar="K",
                   help="also L1-physics, branching L1's K best actions in physics at each decision (0: not run)")
    p.add_argument("--physics-worlds", type=int, default=0, metavar="W",
                   help="L1-physics branches in W worlds drawn per episode from --physics-gap (the planner's guesses, "
                        "not the episode's world), an action scored by the share it holds in (0: in the model)")
    p.add_argument("--physics-gap", default=None, choices=list(world_lib.LEVELS), metavar="LEVEL",
                   help="with --physics-worlds: the gap they are drawn from (default: --world's level)")
    p.add_argument("--chunk", type=int, default=CHUNK, metavar="N",
                   help=f"episodes per lockstep (default {CHUNK}); each finished chunk is kept in "
                        "results/envelope/<set>.parts/, and the same command run again continues from them")
    common.add_bases_argument(p)


# ---------------------------------------------------------------------------------------------------- chunks
def parts_key(ctx, args: argparse.Namespace, kinds: list[str], config=None, worlds=None) -> str:
    """A hash (16 hex digits) of everything a chunk's outcomes depend on: the context (`common.fingerprint`: the
    library and model sources, the model's digest, the episodes' names, the RL policy), this file, the physics'
    `PhysicsConfig` (`config`: the contact controller), the episodes' worlds (None: nominal), the sequences' kinds,
    --random, --seed, --physics-lookahead, --bases, --chunk and L1-physics's worlds (`branch_worlds`)."""
    h = hashlib.sha256(common.fingerprint(ctx).encode())
    h.update(repr(config).encode())
    if worlds is not None:
        h.update(world_lib.digest(worlds).encode())
    h.update(pathlib.Path(__file__).read_bytes())
    h.update(repr((kinds, args.random, args.seed, args.physics_lookahead, tuple(args.bases), args.chunk)).encode())
    if getattr(args, "physics_worlds", 0):
        h.update(repr(("worlds", args.physics_worlds, args.physics_gap)).encode())
    return h.hexdigest()[:16]


def branch_worlds(args: argparse.Namespace, run: Run) -> dict:
    """L1-physics's world options (`gsp_jax.planners` `L1-physics`: worlds, gap) of --physics-worlds and
    --physics-gap (default: the run's --world level); {} to branch in the model. SystemExit naming a bad one."""
    if args.physics_worlds < 0:
        raise SystemExit(f"envelope: --physics-worlds must be >= 0, got {args.physics_worlds}")
    if not args.physics_worlds:
        if args.physics_gap is not None:
            raise SystemExit("envelope: --physics-gap is for --physics-worlds W (W >= 1)")
        return {}
    if not args.physics_lookahead:
        raise SystemExit("envelope: --physics-worlds is L1-physics's: give --physics-lookahead K too")
    args.physics_gap = args.physics_gap or run.world
    if args.physics_gap == "nominal":
        raise SystemExit("envelope: --physics-worlds needs a gap to draw them from: --physics-gap gap|wide (or "
                         "--world gap|wide)")
    return dict(worlds=args.physics_worlds, gap=args.physics_gap)


def part_path(folder: pathlib.Path, key: str, idx: np.ndarray) -> pathlib.Path:
    """Where the chunk of episodes `idx` (0-based, consecutive) is kept: <folder>/<key>_episodes<first>-<last>.npz,
    1-based."""
    return folder / f"{key}_episodes{idx[0] + 1}-{idx[-1] + 1}.npz"


def outcomes(results, n_seg: int, T: int) -> dict[str, np.ndarray]:
    """What the classification and the summary read of a chunk's `Result`s (G groups on n episodes), stacked:
    fell (G, n) bool, angle_error (G, n) [deg], actions and grasps (G, n, T) int, fall_time (G, n) [s] (-1: held),
    and reached (G, n, T, nq), the configuration at the end of each of the first T segments (before each decision
    t >= 1 and at the hold's start; `n_seg` control ticks a segment), not the whole traces."""
    out = {k: np.stack([np.asarray(getattr(r, k)) for r in results]) for k in FIELDS if k != "reached"}
    out["reached"] = np.stack([np.asarray(r.qpos)[:, n_seg - 1 :: n_seg][:, :T] for r in results])
    return out


def load_part(path: pathlib.Path, shape: tuple[int, int]) -> dict[str, np.ndarray] | None:
    """A kept chunk's outcomes (`outcomes`, and its physics time "seconds" [s]), or None where there is none; one
    that cannot be read (truncated, not an .npz of these fields) or whose (G, n) is not `shape` is named in a warning
    and None returned, so that its episodes run again."""
    if not path.exists():
        return None
    try:
        with np.load(path) as d:
            part = {k: d[k] for k in (*FIELDS, "seconds")}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as e:
        warnings.warn(f"{path}: cannot be read ({e}): running its episodes again", stacklevel=2)
        return None
    if any(part[k].shape[:2] != shape for k in FIELDS):
        warnings.warn(f"{path}: not the outcomes of {shape[0]} sequences x {shape[1]} episodes: running its episodes "
                      "again", stacklevel=2)
        return None
    return part


def stopped(idx: np.ndarray, n: int, c: int, n_chunks: int, error: BaseException, kept: int,
            folder: pathlib.Path) -> str:
    """The one line that says where a run stopped: the failed chunk `c` (0-based) of episodes `idx` of `n`, the
    cause (the exception's type and the first line of its message) and the `kept` finished episodes in `folder`."""
    message = str(error).strip().splitlines()
    cause = type(error).__name__ + (f": {message[0]}" if message else "")
    first, last = idx[0] + 1, idx[-1] + 1
    where = f"episode {first}" if first == last else f"episodes {first}–{last}"
    return (f"envelope: stopped in {where} of {n} (chunk {c + 1} of {n_chunks}): "
            f"{cause}; {kept} finished episodes kept in {folder} (the same command continues from them)")


def results_folders(args: argparse.Namespace) -> list[tuple[str, ...]]:
    """The `results_dir` parts of the folders it writes: `python -m experiments` locks them before its set-up."""
    return [("envelope",)]


# ---------------------------------------------------------------------------------------------------- main
def main(args: argparse.Namespace, run: Run) -> None:
    common.check_planners(args.policies, "--policies", "c")
    common.check_planners(args.bases, "--bases")
    if args.random < 0:
        raise SystemExit(f"envelope: --random must be >= 0, got {args.random}")
    if args.physics_lookahead < 0:
        raise SystemExit(f"envelope: --physics-lookahead must be >= 0, got {args.physics_lookahead}")
    if args.chunk < 1:
        raise SystemExit(f"envelope: --chunk must be >= 1, got {args.chunk}")
    hedge = branch_worlds(args, run)
    reads = gsp_planners.context_flags([*args.policies,
                                        *(["L1-physics", *args.bases] if args.physics_lookahead else [])])
    ctx = evaluation.context(args.set, args.episodes, args.policy_dir, model=run.model, results=common.RESULTS,
                             learned=run.learned,
                             # the tables where a planner or the random sequences read them; every sequence is
                             # scored in them, or else by the surrogate (`rollout.sequence_scores`: a space whose
                             # tables are too large to build, planned by `search`)
                             **(reads | dict(tables=reads["tables"] or args.random > 0,
                                             nominal=reads["nominal"] or reads["rl"])))
    sur, N, T = ctx.surrogate, len(ctx.names), ctx.batch.n_steps
    planners = [p for p in args.policies if p != "rl" or ctx.rl is not None]  # a model without a PPO policy: no RL row
    planners += ["L1-physics"] if args.physics_lookahead else []
    keys = jax.random.split(jax.random.PRNGKey(args.seed), N * args.random).reshape(N, args.random, 2)
    holds = jnp.where(jnp.arange(args.random) % 2 == 0, 0.0, 0.8)
    rand = None if not args.random else jax.vmap(jax.vmap(dp.random_sequence, (None, None, 0, None, 0)),
                                                 (0, 0, 0, None, None))(
        ctx.tables, ctx.batch.start_grasp, keys, sur.reward_config.r_min, holds)  # (N, R, T)
    kinds = planners + [f"random{r}" for r in range(args.random)]
    phys = physics.Physics(sur, run.physics_config())
    n_seg, tick = phys.n_segment, phys.timestep
    pieces = distributed.chunks(N, args.chunk)
    folder = run.results_dir("envelope") / f"{args.set}.parts"
    worlds = run.worlds(ctx.batch, sur.hand)  # None: the nominal world
    key = parts_key(ctx, args, kinds, phys.config, worlds)
    mine = distributed.share(len(pieces))  # this process's chunks (all of them for one)
    done = {c: part for c in mine
            if (part := load_part(part_path(folder, key, pieces[c]), (len(kinds), len(pieces[c])))) is not None}
    print(f"envelope: {N} episodes of '{args.set}' x {len(kinds)} sequences = {N * len(kinds)} episodes in C MuJoCo, "
          f"{len(pieces)} chunk{'s' * (len(pieces) > 1)} of up to {args.chunk} episodes (JAX on "
          f"{jax.default_backend()})" + (f"; process {distributed.rank()} of {distributed.count()} runs chunks "
                                         f"{mine.start + 1}-{mine.stop}" if distributed.count() > 1 else ""),
          flush=True)
    if done:
        print(f"  reusing {sum(len(pieces[c]) for c in done)} finished episodes of {N} from {folder}", flush=True)
    for c in mine:
        idx = pieces[c]
        if c in done:
            continue
        try:
            sub = ctx.select(idx)
            groups = [gsp_planners.make(sub, name, dict(k=args.physics_lookahead or 1, bases=tuple(args.bases),
                                                         **hedge))
                      for name in planners]
            groups += [(policies.SequencePolicy(rand[idx, r]), 0) for r in range(args.random)]
            t0 = time.perf_counter()
            res = phys.simulate_many(groups, sub.batch, backend="c", progress=True, world=world_lib.rows(worlds, idx))
            part = dict(outcomes(res, n_seg, T), seconds=np.float64(time.perf_counter() - t0))
            files.savez(part_path(folder, key, idx), **part)
        except BaseException as e:
            kept = sum(len(pieces[i]) for i in done)
            print(stopped(idx, N, c, len(pieces), e, kept, folder), file=sys.stderr, flush=True)
            raise
        done[c] = part
    done = distributed.gather_merged(done)  # every process's chunks
    if not distributed.is_main():
        return  # process 0 classifies, writes and records
    sim = {k: np.concatenate([done[c][k] for c in range(len(pieces))], axis=1) for k in FIELDS}
    t_phys = float(sum(done[c]["seconds"] for c in done))  # this result's physics, over the runs that made it
    fell, angle = sim["fell"], sim["angle_error"]
    actions = jnp.asarray(sim["actions"])  # (G, N, T)
    starts = jnp.broadcast_to(ctx.batch.start_grasp, actions.shape[:2])
    if ctx.tables is not None:
        rewards, returns, hold = jax.vmap(jax.vmap(dp.sequence_scores), (None, 0, 0))(ctx.tables, starts, actions)
    else:
        rewards, returns, hold = jax.jit(jax.vmap(jax.vmap(lambda ep, a: rollout.sequence_scores(sur, ep, a)),
                                                  (None, 0)))(ctx.batch, actions)
    feasible = np.asarray(jnp.all(rewards > sur.reward_config.r_min, -1))  # (G, N)
    returns, hold = np.asarray(returns), np.asarray(hold)
    print(f"  physics {t_phys:.0f} s; {int(fell.sum())} falls of {fell.size} to classify ...", flush=True)
    episodes = scenario.unstack(ctx.batch)
    falls = [(g, e) for g in range(len(kinds)) for e in range(N) if fell[g, e]]
    t1 = time.perf_counter()

    def reached(g, e):  # the configurations before each decision t >= 1 and at the hold's start; rows before the fall
        fall_tick = int(round(float(sim["fall_time"][g, e]) / tick))
        return sim["reached"][g, e], int(np.sum(np.arange(1, T + 1) * n_seg - 1 < fall_tick))

    verdicts = classify(episodes, [(e, [int(x) for x in sim["grasps"][g, e]], *reached(g, e))
                                   for g, e in falls], args.jobs or c_backend.available_cores(), sur.model)
    classes = {ge: v[0] for ge, v in zip(falls, verdicts)}
    summary = summarise(kinds, fell, angle, feasible, returns, classes, {ge: v[3] for ge, v in zip(falls, verdicts)},
                        hold if sur.learned is not None else None)
    verdict = dict(zip(falls, verdicts))

    def row(g, e):
        r = dict(kind=kinds[g], episode=ctx.names[e], fell=bool(fell[g, e]), angle_deg=float(angle[g, e]),
                 surrogate_feasible=bool(feasible[g, e]), surrogate_return=float(returns[g, e]),
                 surrogate_hold=float(hold[g, e]),
                 grasps=[int(x) for x in sim["grasps"][g, e]])
        if (g, e) in verdict:
            r["oracle"] = dict(zip(("class", "worst_point", "worst_ratio", "early", "reached_worst_point",
                                    "reached_worst_ratio"), verdict[g, e]))
            r["fall_time"] = float(sim["fall_time"][g, e])
        return r

    out = dict(set=args.set, episodes=ctx.names, kinds=kinds, physics_s=t_phys, oracle_s=time.perf_counter() - t1,
               platform=jax.default_backend(), rl_policy=ctx.rl_source, summary=summary, world=run.world_name,
               sequences=[row(g, e) for g in range(len(kinds)) for e in range(N)],
               **({} if worlds is None else dict(world_seed=run.world_seed, worlds=world_lib.as_rows(worlds))),
               **({} if not hedge else dict(physics_worlds=args.physics_worlds, physics_gap=args.physics_gap)))
    path = folder.parent / f"{args.set}{f'-worlds{args.physics_worlds}' if hedge else ''}.json"
    files.write_json(path, out)
    print(f"wrote {path}\n")
    run.record_figures(f"envelope_{args.set}{f'_worlds{args.physics_worlds}' if hedge else ''}",
                       dict(episodes=N, random=args.random, summary=summary,
                            **({} if not hedge else dict(physics_worlds=args.physics_worlds,
                                                         physics_gap=args.physics_gap))))
    p = summary["pool"]
    print(f"pool: {p['sequences']} sequences, {p['surrogate_feasible']} surrogate-feasible, of those "
          f"{100 * p['feasible_hold_share']:.1f}% hold; AUC(return: hold vs fall) pooled {p['auc_pooled']:.2f}, "
          f"within episodes {p['auc_within_mean']:.2f} ({p['auc_within_episodes']} episodes); Spearman "
          f"rho(return, -angle) {p['spearman_pooled']:.2f}")
    if "predicted_hold" in p:
        print(f"predicted to hold (feasible, chance to hold >= {PREDICTED_HOLD}): {p['predicted_hold']}, "
              f"of those {100 * p['predicted_hold_share']:.1f}% hold")
    rows = [[k, r["falls"], r["necessary"], r["early"], r["controller"], r["undetermined"], r["regret"],
             r["mean_angle_held_deg"]] for k, r in summary["kinds"].items() if k in planners or args.random <= 4]
    print(table(["sequence", f"falls /{N}", "necessary", "of them early", "controller", "undetermined", "regret",
                 "angle held [deg]"],
                rows, ".2f"))
