"""The online latency of each planner per decision, one unseen episode at a time (`table1 --per-decision`).

    result = run(ctx, names, cached=True)   # {policies: {name: {decision_median_s, decision_p99_s, ...}}, ...}
"""
from __future__ import annotations

import jax
import numpy as np

from experiments import common
from experiments.common import table, timed
from gsp_jax.planning import dp, evaluation, policies
from gsp_jax.planners import registry as planners
from gsp_jax.learning.env import TableModel


LOOKAHEADS = ("L1", "L2")  # the rows whose tree reads each episode's table when cached


def _verified(name: str) -> bool:
    return planners.get(name).group == "verified"


def run(ctx: evaluation.Context, names: list[str], cached: bool, ks=(evaluation.L1_PHYSICS["k"],),
        bases=evaluation.L1_PHYSICS["bases"], config=None) -> dict:
    sur = ctx.surrogate
    step = jax.jit(sur.step)
    act = jax.jit(lambda policy, state: policy.act(state))
    build = jax.jit(lambda ep: dp.build_table(sur, ep))
    backup = jax.jit(dp.backup)
    episodes = [jax.tree.map(lambda x, i=i: x[i], ctx.batch) for i in range(len(ctx.names))]

    # setup per episode, shared by the planners that need it: the table (cached L1/L2, DP optimal) and its backup
    jax.block_until_ready(backup(build(episodes[0]), episodes[0].start_grasp))  # compile both
    tables, t_build, t_backup = [], [], []
    needs_table = ("dp-opt" in names or any(_verified(n) for n in names)
                   or (cached and any(n in LOOKAHEADS for n in names)))
    for i, ep in enumerate(episodes if needs_table else []):
        tab, tb = timed(build, ep)
        sol, tk = timed(backup, tab, ep.start_grasp)
        tables.append((tab, sol))
        t_build.append(tb), t_backup.append(tk)
        print(f"  setup, episode {i}: table {tb:.3f} s, backup {tk * 1e3:.2f} ms", flush=True)

    rows = {}
    for name in names:
        if _verified(name):
            for k in ks:
                label = name if len(ks) == 1 else f"{name} k={k}"
                table = cached or "dp-opt" in bases  # the root's table (cached L1), DP optimal's table and backup
                setup = [table * tb + ("dp-opt" in bases) * tk for tb, tk in zip(t_build, t_backup)]
                rows[label] = physics_lookahead(ctx, name, k, bases, cached, setup, config)
            continue
        base, _ = planners.make(ctx, name, dict(cached=False))  # dp-base, rl, continuous lookahead: episode-independent

        def policy_for(i):
            if name == "dp-opt":
                return policies.TablePolicy(tables[i][1].policy)
            if cached and name in LOOKAHEADS:
                return base.replace(inner=TableModel(tables[i][0], sur.space))
            return base

        setup = ([b + k for b, k in zip(t_build, t_backup)] if name == "dp-opt" else
                 list(t_build) if cached and name in LOOKAHEADS else [0.0] * len(episodes))
        warm = sur.reset(episodes[0])
        jax.block_until_ready(step(warm, act(policy_for(0), warm)))  # compile
        decide, stepping, per_episode, returns = [], [], [], []
        for i, ep in enumerate(episodes):
            policy, state, spent, ret = policy_for(i), sur.reset(ep), setup[i], 0.0
            for _ in range(ep.n_steps):
                action, t_act = timed(act, policy, state)
                (state, reward, done), t_step = timed(step, state, action)
                decide.append(t_act), stepping.append(t_step)
                spent, ret = spent + t_act + t_step, ret + float(reward)
                if bool(done):
                    break
            per_episode.append(spent), returns.append(ret)
        d = np.asarray(decide)
        rows[name] = dict(decisions=len(d), decision_median_s=float(np.median(d)),
                          decision_p99_s=float(np.percentile(d, 99)),
                          setup_median_s=float(np.median(setup)), step_median_s=float(np.median(stepping)),
                          episode_median_s=float(np.median(per_episode)), returns=returns)
        print(f"  {name:8s} decision median {rows[name]['decision_median_s'] * 1e3:8.2f} ms, p99 "
              f"{rows[name]['decision_p99_s'] * 1e3:8.2f} ms ({len(d)} decisions), "
              f"setup {rows[name]['setup_median_s']:.3f} s",
              flush=True)
    device = jax.local_devices()[0]
    return dict(platform=device.platform, device=str(device.device_kind), episodes=ctx.names,
                lookahead="cached" if cached else "continuous", policies=rows, paper=common.PAPER)


def physics_lookahead(ctx: evaluation.Context, name: str, k: int, bases, cached: bool, setup, config=None) -> dict:
    """`name` (L1-physics) with k candidates on each episode alone in C MuJoCo, warm (episode 0 run once before):
    per decision the `Decision.seconds` of its call, per episode setup + its decisions."""
    from gsp_jax import physics
    from gsp_jax.physics import c_backend

    phys = physics.Physics(ctx.surrogate, config or physics.PhysicsConfig())
    # the engine's own speed on this machine: mj_step alone on one core, over the states of a four-tip run
    first = ctx.select([0])
    log = []
    c_backend.simulate(phys, [planners.make(first, "four-tips")], first.batch, cores=1, workers=1, engine_log=log)
    rate, _ = c_backend.engine_alone(phys, first.batch, log)

    def episode(i):
        one = ctx.select([i])
        policy, axis = planners.make(one, name, dict(cached=cached, k=k, bases=bases))
        res, wall = timed(lambda: phys.simulate_batch(policy, one.batch, axis, backend="c"))
        return [d.seconds for d in policy.decisions], [d.steps for d in policy.decisions], wall, res

    print(f"  {name} k={k}: compiling (episode 0) ...", flush=True)
    episode(0)
    decide, steps, per_episode, engine, simulated, falls, angles = [], [], [], [], [], 0, []
    for i in range(len(ctx.names)):
        d, n, wall, res = episode(i)
        decide += d
        steps += n
        per_episode.append(setup[i] + sum(d)), simulated.append(wall), engine.append(sum(n) / rate)
        falls += int(np.sum(res.fell))
        angles.append(float(np.asarray(res.angle_error)[0]))
        print(f"  {name} k={k}, episode {i}: {len(d)} decisions, median {np.median(d):.3f} s, planning "
              f"{per_episode[-1]:.2f} s, simulated in {wall:.2f} s, {'FELL' if res.fell[0] else 'held'}; its branches' "
              f"{sum(n):,} physics steps take the engine alone {engine[-1]:.2f} s on one core", flush=True)
    d, n = np.asarray(decide), np.asarray(steps)
    return dict(k=k, bases=list(bases), decisions=len(d), decision_median_s=float(np.median(d)),
                decision_p99_s=float(np.percentile(d, 99)), setup_median_s=float(np.median(setup)), step_median_s=0.0,
                episode_median_s=float(np.median(per_episode)), simulated_median_s=float(np.median(simulated)),
                falls=falls, angle_error_deg=angles, cores=c_backend.available_cores(),
                engine_steps_per_s_one_core=rate, decision_steps_median=float(np.median(n)),
                engine_decision_median_s=float(np.median(n) / rate), engine_episode_median_s=float(np.median(engine)))


def print_result(result: dict) -> None:
    headers = ["planner", "setup / episode [s]", "decision median [ms]", "decision p99 [ms]", "surrogate step [ms]",
               "episode [s]", "engine alone: decision [ms]", "engine alone: episode [s]", "paper, episode [s]"]
    engine = lambda r, key, scale: f"{r[key] * scale:.2f}" if key in r else "-"  # noqa: E731
    rows = [[name, f"{r['setup_median_s']:.3f}", f"{r['decision_median_s'] * 1e3:.2f}",
             f"{r['decision_p99_s'] * 1e3:.2f}",
             f"{r['step_median_s'] * 1e3:.2f}", f"{r['episode_median_s']:.3f}",
             engine(r, "engine_decision_median_s", 1e3), engine(r, "engine_episode_median_s", 1.0),
             common.PAPER["table1_s"].get(name.split()[0].removesuffix("-physics"), "-")]
            for name, r in result["policies"].items()]
    cores = {r["cores"] for r in result["policies"].values() if "cores" in r}
    print(f"Per-decision latency, one episode at a time ({result['device']}, lookahead {result['lookahead']}, "
          f"{len(result['episodes'])} episodes; medians; paper: {common.PAPER['table1_machine']}; engine alone: "
          f"mj_step of the same physics steps on one core of this machine, physics planners on "
          f"{', '.join(map(str, cores)) or '-'} cores)")
    print(table(headers, rows, ".2f"))
