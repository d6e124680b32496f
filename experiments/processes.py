"""`python -m experiments --processes N <command>`: N processes of `<command>` on this host, one run.

Each process gets an equal contiguous share of this process's CPU cores (its affinity) and, where there are GPUs,
one GPU (process p the p-th, round robin; processes that share a GPU share its memory equally); process 0 also runs
the coordinator of JAX's distributed runtime on a free local port (`gsp_jax.core.distributed` reads the three variables
set here). Process 0's output is this command's; the others' goes to results/processes/rank<p>.log. When a process
fails, the others are stopped at once and the run ends with an error that names its rank, its exit status and the
last lines of its output.

On a cluster, start the command with `srun` (or `mpirun`) instead: `jax.distributed` reads the cluster by itself
(docs/scale.md)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

from experiments.common import RESULTS
from gsp_jax.core import distributed

LOG_DIR = RESULTS / "processes"
POLL_S = 0.2  # [s] how often the launcher looks at its processes
TAIL_LINES = 15  # lines of a failed process's output shown in the error


def free_port() -> int:
    """A TCP port free on this host now (the coordinator's)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def core_shares(n: int, cores: list[int] | None = None) -> list[list[int]]:
    """Each of n processes' CPU cores: contiguous equal shares of `cores` (default: this process's affinity); with
    fewer cores than processes, processes share them round robin."""
    cores = sorted(os.sched_getaffinity(0)) if cores is None else list(cores)
    if len(cores) < n:
        return [[cores[p % len(cores)]] for p in range(n)]
    return [[cores[i] for i in share] for share in distributed.split(len(cores), n)]


def gpus() -> list[str]:
    """The GPUs this host lets us use: CUDA_VISIBLE_DEVICES's entries, else those `nvidia-smi -L` lists, else none."""
    visible = os.environ.get("CUDA_VISIBLE_DEVICES")
    if visible is not None:
        return [g for g in visible.split(",") if g.strip()]
    if os.environ.get("JAX_PLATFORMS", "").strip().lower() == "cpu":
        return []
    try:
        out = subprocess.run(["nvidia-smi", "-L"], capture_output=True, text=True, timeout=20).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    return [str(i) for i, line in enumerate(out.splitlines()) if line.startswith("GPU ")]


def launch(n: int, words: list[str], cores: list[int] | None = None) -> int:
    """Run `python -m experiments <words>` as n processes of one run, sharing `cores` (default: this process's
    affinity); 0 when all succeed, else raises SystemExit with the first failed process's rank, status and
    output's last lines."""
    if n < 1:
        raise SystemExit(f"--processes must be >= 1, got {n}")
    address = f"127.0.0.1:{free_port()}"
    shares, devices = core_shares(n, cores), gpus()
    LOG_DIR.mkdir(parents=True, exist_ok=True)
    procs, logs = [], []
    print(f"processes: {n} on this host, coordinator {address}; cores {[f'{s[0]}-{s[-1]}' for s in shares]}"
          + (f"; GPUs {[devices[p % len(devices)] for p in range(n)]}" if devices else "") + f"; ranks 1.. log to "
          f"{LOG_DIR}/", flush=True)
    for p in range(n):
        env = dict(os.environ, **{distributed.ENV_COORDINATOR: address, distributed.ENV_NUM_PROCESSES: str(n),
                                  distributed.ENV_PROCESS_ID: str(p)})
        if devices:
            env["CUDA_VISIBLE_DEVICES"] = devices[p % len(devices)]
            sharing = -(-n // len(devices))  # processes on one GPU: each takes its part of the memory, not 75%
            if sharing > 1 and "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ:
                env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{0.9 / sharing:.3f}"
        log = None if p == 0 else open(LOG_DIR / f"rank{p}.log", "w")
        logs.append(log)
        cores = shares[p]
        procs.append(subprocess.Popen([sys.executable, "-m", "experiments", *words], env=env,
                                      stdout=log, stderr=subprocess.STDOUT if log else None,
                                      preexec_fn=lambda cores=cores: os.sched_setaffinity(0, cores)))
    try:
        while True:
            codes = [proc.poll() for proc in procs]
            failed = [p for p, c in enumerate(codes) if c not in (None, 0)]
            if failed:
                p = failed[0]
                _stop(procs)
                raise SystemExit(_failure(p, codes[p]))
            if all(c == 0 for c in codes):
                return 0
            time.sleep(POLL_S)
    except KeyboardInterrupt:
        _stop(procs)
        raise
    finally:
        for log in logs:
            if log is not None:
                log.close()


def _stop(procs: list[subprocess.Popen]) -> None:
    """Terminate every process still running, then kill those that have not ended within 10 s."""
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
    deadline = time.monotonic() + 10
    for proc in procs:
        try:
            proc.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _failure(rank: int, code: int) -> str:
    """The error of a failed run: the rank, how it ended, and its log's last lines (rank 0's output is above)."""
    how = f"was killed by signal {-code} ({signal.Signals(-code).name})" if code < 0 else f"exited with status {code}"
    text = f"processes: process {rank} {how}; the others were stopped"
    if rank > 0:
        lines = (LOG_DIR / f"rank{rank}.log").read_text(errors="replace").splitlines()[-TAIL_LINES:]
        text += f". The end of its output ({LOG_DIR}/rank{rank}.log):\n" + "\n".join("  " + s for s in lines)
    return text
