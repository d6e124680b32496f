"""Fig. 4b's runner (`experiments.paper.fig4b.evaluate`): in C MuJoCo every policy runs in one lockstep, and each gives
what it gives alone (the controller program of another batch size: float reassociation only)."""
from __future__ import annotations

import json
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import launch  # noqa: E402

from experiments.paper import fig4b  # noqa: E402
from gsp_jax.planning import evaluation  # noqa: E402
from gsp_jax.planning import policies  # noqa: E402
from gsp_jax.model import scenario  # noqa: E402
from gsp_jax.learning.env import observation_size  # noqa: E402
from gsp_jax.ppo import networks as nets  # noqa: E402

T = 3


def _context(sur) -> evaluation.Context:
    """Two short evaluation episodes; DP baseline = a fixed sequence (no DP here), RL = a random-weight network."""
    a, b = scenario.eval_set_a(), scenario.eval_set_b()
    episodes = {"shift+4mm_-1Nm": a["shift+4mm_-1Nm"].head(T), "mass0.5m0_comy-2cm": b["mass0.5m0_comy-2cm"].head(T)}
    networks = nets.make_networks(observation_size(sur.space, T, sur.hand.n_joints), sur.n_actions,
                                  nets.NetworkConfig(hidden=(32, 32)))
    rl = policies.NetworkPolicy(networks.init(jax.random.PRNGKey(5)), networks, sur.space)
    sequence = jnp.array([3, 0, 5], jnp.int32)  # a grasp change, the null action, another change
    return evaluation.Context(sur, "test", list(episodes), scenario.stack(list(episodes.values())), None, None,
                              sequence, rl, "random weights")


def test_policies_in_one_lockstep_give_what_they_give_alone(sur, tmp_path):
    ctx = _context(sur)
    names = ["dp-base", "rl"]
    out = tmp_path / "lockstep"
    out.mkdir()
    both = fig4b.evaluate(ctx, names, out, fresh=True, backend="c")
    assert sorted(p.name for p in out.glob("*.json")) == ["dp-base.json", "rl.json"]  # each policy saved
    runs = {1: {}}
    for name in names:
        alone = tmp_path / name
        alone.mkdir()
        runs[1][name] = one = fig4b.evaluate(ctx, [name], alone, fresh=True, backend="c")[name]
        assert one["falls"] == both[name]["falls"], name
        for a, b in zip(one["per_episode"], both[name]["per_episode"]):
            assert a["grasps"] == b["grasps"] and a["fell"] == b["fell"], name
            if not a["fell"]:
                assert abs(a["angle_error_deg"] - b["angle_error_deg"]) < 0.5, name
    for i, row in enumerate(runs[1]["dp-base"]["per_episode"]):  # the sequence reached the physics
        grasp, expected = ctx.batch.start_grasp[i], []
        for action in ctx.nominal_actions:
            grasp = sur.space.apply(grasp, action)[0]
            expected.append(int(grasp))
        assert row["grasps"] == expected


NET_PLUGIN = '''"""A planner that decides in JAX at every waypoint of the physics: a random-weight actor network."""
import jax

from gsp_jax import planners
from gsp_jax.planning import policies
from gsp_jax.learning.env import observation_size
from gsp_jax.ppo import networks as nets


@planners.register("net")
def _net(ctx):
    sur = ctx.surrogate
    networks = nets.make_networks(observation_size(sur.space, ctx.batch.n_steps, sur.hand.n_joints), sur.n_actions,
                                  nets.NetworkConfig(hidden=(32, 32)))
    return policies.NetworkPolicy(networks.init(jax.random.PRNGKey(5)), networks, sur.space), None
'''


def test_two_processes_give_one_processs_outcomes_bit_for_bit(tmp_path):
    """`--processes 2 fig4b` on two episodes: each process runs one chunk (the four tips and a network that decides
    in JAX), process 0 gathers and alone writes; every episode's outcome equals one process's run of the same
    chunks, to the last bit."""
    line = ["fig4b", "--set", "eval", "--episodes", "2", "--policies", "four-tips", "net", "--chunk", "1", "--paper"]
    out = {}
    for n in (1, 2):
        folder = tmp_path / f"p{n}"
        proc = launch.run(folder, n, line, {"net.py": NET_PLUGIN})
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
        saved = {name: json.loads((folder / f"results/fig4b/{name}.json").read_text()) for name in ("four-tips", "net")}
        out[n] = {name: (r["per_episode"], r["mean_deg"], r["falls"]) for name, r in saved.items()}
        assert [r["episode"] for r in saved["net"]["per_episode"]] == saved["net"]["episodes"]
    assert "process 1 of 2 runs chunks 2-2 of 2" in (tmp_path / "p2/results/processes/rank1.log").read_text()
    assert not (tmp_path / "p1/results/processes").exists()
    assert json.dumps(out[2], sort_keys=True) == json.dumps(out[1], sort_keys=True)
