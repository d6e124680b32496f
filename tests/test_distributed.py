"""`gsp_jax.core.distributed` in one process and `--processes`'s parts that need no second process (the runs of two
processes: tests/test_envelope_resume.py, tests/test_fig4b.py); one process over two local devices."""
import os
import subprocess
import sys

import numpy as np
import pytest
import tolerances as tol

from experiments import processes
from experiments.cli import processes_asked
from gsp_jax.core import distributed


@pytest.mark.parametrize("n,parts", [(0, 1), (1, 3), (7, 1), (7, 2), (7, 3), (12, 4), (5, 8)])
def test_split_gives_contiguous_shares_in_order_that_cover_every_item_once(n, parts):
    shares = distributed.split(n, parts)
    assert len(shares) == parts
    assert [i for s in shares for i in s] == list(range(n))
    sizes = [len(s) for s in shares]
    assert max(sizes) - min(sizes) <= 1 and sizes == sorted(sizes, reverse=True)


def test_split_refuses_bad_arguments():
    with pytest.raises(ValueError, match="parts >= 1"):
        distributed.split(3, 0)


def test_one_process_is_rank_0_of_1_and_gathers_its_own():
    assert not distributed.requested()
    assert (distributed.rank(), distributed.count(), distributed.is_main()) == (0, 1, True)
    assert distributed.share(5) == range(5)
    assert distributed.gather({"a": 1}) == [{"a": 1}] and distributed.total(2.5) == 2.5
    distributed.barrier("nothing to wait for")


def test_processes_flag_is_read_before_the_command_only():
    assert processes_asked(["--processes", "2", "envelope", "--set", "eval"]) == (2, ["envelope", "--set", "eval"])
    assert processes_asked(["--processes=3", "--record", "dp"]) == (3, ["--record", "dp"])
    assert processes_asked(["envelope", "--processes", "2"]) == (None, ["envelope", "--processes", "2"])
    for bad in ("two", "0", "-1"):
        with pytest.raises(SystemExit, match=f"--processes: expects a number of processes >= 1, got '{bad}'"):
            processes_asked(["--processes", bad, "dp"])


def test_each_process_gets_an_equal_contiguous_share_of_the_cores():
    assert processes.core_shares(2, [0, 1, 2, 3]) == [[0, 1], [2, 3]]
    assert processes.core_shares(3, [4, 5, 6, 7]) == [[4, 5], [6], [7]]
    assert processes.core_shares(3, [0, 1]) == [[0], [1], [0]]  # fewer cores than processes: shared round robin


def test_bad_runtime_settings_are_named(monkeypatch):
    monkeypatch.setenv(distributed.ENV_COORDINATOR, "127.0.0.1:1")
    monkeypatch.setenv(distributed.ENV_NUM_PROCESSES, "2")
    monkeypatch.setenv(distributed.ENV_PROCESS_ID, "5")
    with pytest.raises(distributed.DistributedError, match="GSP_JAX_PROCESS_ID=5 is not one of the "
                                                           "GSP_JAX_NUM_PROCESSES=2 processes"):
        distributed.initialize()
    monkeypatch.setenv(distributed.ENV_PROCESS_ID, "x")
    with pytest.raises(distributed.DistributedError, match="must be integers"):
        distributed.initialize()


def test_chunks_are_fixed_runs_of_size_whatever_the_processes():
    assert [c.tolist() for c in distributed.chunks(5, 2)] == [[0, 1], [2, 3], [4]]
    assert distributed.chunks(0, 3) == []
    with pytest.raises(ValueError, match="size >= 1"):
        distributed.chunks(4, 0)


def test_chunk_size_is_one_chunk_per_process_by_default():
    assert distributed.chunk_size(7) == 7 and distributed.chunk_size(7, 3) == 3  # one process
    with pytest.raises(ValueError, match="must be >= 1, got 0"):
        distributed.chunk_size(7, 0)


def test_map_chunks_joins_each_chunks_result_in_order():
    seen = []

    def fn(idx):
        seen.append(idx.tolist())
        return dict(sq=idx ** 2, pair=(idx, np.stack([idx, -idx], -1)))

    out = distributed.map_chunks(fn, 7, 3)
    assert seen == [[0, 1, 2], [3, 4, 5], [6]]  # one call per fixed chunk, the last one shorter
    np.testing.assert_array_equal(out["sq"], np.arange(7) ** 2)
    np.testing.assert_array_equal(out["pair"][1], np.stack([np.arange(7), -np.arange(7)], -1))
    with pytest.raises(ValueError, match="n >= 1"):
        distributed.map_chunks(fn, 0, 3)


DEVICES = '''
import sys
import jax, numpy as np
import gsp_jax
gsp_jax.enable_cache()  # the run's test cache (GSP_JAX_CACHE, set by conftest)
from gsp_jax.planning import evaluation
from gsp_jax.solvers import ik
from gsp_jax.model import scenario
from gsp_jax.surrogate import step as surrogate

sur = surrogate.Surrogate(ik_config=ik.IKConfig(lanes=False), learned=False)
episodes = {k: e.head(2) for k, e in list(scenario.episode_set("eval").items())[:3]}
tables = evaluation.dp_tables(sur, "eval", episodes, batch_size=2, cache=None)
n = int(sys.argv[1])
batches = evaluation.table_builder()(sur, scenario.stack(list(episodes.values())[:1] * 2 * n))  # as dp_tables calls it
assert len(jax.local_devices()) == len(batches.reward.sharding.device_set) == n
np.savez(f"tables{sys.argv[1]}.npz", **{k: np.asarray(v) for k, v in vars(tables).items() if v is not None})
'''


def test_dp_tables_over_two_local_devices_equal_one_devices(tmp_path):
    """One process with two (CPU) devices builds a set's tables with the episodes split over both (a batch of two
    on each per call, the last one filled up: `distributed.over_local_devices`): one device's tables, the IK to the
    last bit and the rewards within the solvers' precision (XLA's partitioned program fuses the wrench terms
    otherwise: float reassociation only)."""
    script = tmp_path / "devices.py"
    script.write_text(DEVICES)
    for n in (1, 2):
        proc = subprocess.run([sys.executable, str(script), str(n)], capture_output=True, text=True, timeout=900,
                              cwd=tmp_path, env=dict(os.environ, JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES=str(n)))
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    with np.load(tmp_path / "tables1.npz") as one, np.load(tmp_path / "tables2.npz") as two:
        assert sorted(one.files) == sorted(two.files) and one["reward"].shape[0] == 3
        for field in ("next_grasp", "terminal"):
            assert np.array_equal(one[field], two[field]), field
        tol.assert_close_with_rare_ties(two["ik_error"], one["ik_error"], tol.IK_ATOL, "ik_error",
                                        tol.small_sample_tie_fraction(one["ik_error"].size))
        tol.assert_close_with_rare_ties(two["reward"], one["reward"], tol.REWARD_ATOL, "reward",
                                        tol.small_sample_tie_fraction(one["reward"].size))


GATHER = '''
import numpy as np
from gsp_jax import distributed

assert distributed.initialize() and distributed.count() == 2
p = distributed.rank()
big = np.arange(3 * distributed.PIECE_BYTES // 8 + 5, dtype=np.float64) * (p + 1)  # three pieces and a bit
for _ in range(2):  # a second gather of the same shape: its own keys
    every = distributed.gather({"rank": p, "big": big, "empty": b""})
    assert [e["rank"] for e in every] == [0, 1]
    for q, e in enumerate(every):
        assert np.array_equal(e["big"], np.arange(big.size, dtype=np.float64) * (q + 1)) and e["empty"] == b""
assert distributed.gather(None) == [None, None] and distributed.total(p + 0.5) == 2.0
print("gathered", p)
'''


def test_gather_moves_values_larger_than_a_piece_bit_for_bit_between_two_processes(tmp_path):
    """Two processes of one runtime (CPU): `gather` returns both processes' values in rank order on each, a value of
    several key-value pieces intact, twice in a row and for None."""
    from experiments.processes import free_port

    script = tmp_path / "gather.py"
    script.write_text(GATHER)
    env = dict(os.environ, JAX_PLATFORMS="cpu", **{distributed.ENV_COORDINATOR: f"127.0.0.1:{free_port()}",
                                                   distributed.ENV_NUM_PROCESSES: "2"})
    procs = [subprocess.Popen([sys.executable, str(script)], cwd=tmp_path, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True,
                              env=dict(env, **{distributed.ENV_PROCESS_ID: str(p)}))
             for p in range(2)]
    outs = [proc.communicate(timeout=300)[0] for proc in procs]
    for p, (proc, out) in enumerate(zip(procs, outs)):
        assert proc.returncode == 0 and f"gathered {p}" in out, out[-3000:]
