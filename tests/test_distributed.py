"""`gsp_jax.distributed` in one process and `--processes`'s parts that need no second process (the runs of two
processes: tests/test_envelope_resume.py)."""
import pytest

from experiments import processes
from experiments.__main__ import processes_asked
from gsp_jax import distributed


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
