"""Several processes, one run: JAX's multi-controller runtime, each process's share of a batch, and the shares
gathered back in process order; and one process's batch split over its local devices (`over_local_devices`).

A process is one of several when its environment says so: `python -m experiments --processes N` sets
`GSP_JAX_COORDINATOR` (host:port), `GSP_JAX_NUM_PROCESSES` and `GSP_JAX_PROCESS_ID` for each process it starts;
under Slurm (`srun`, more than one task) or Open MPI, `jax.distributed.initialize()` reads the cluster by itself.
Otherwise there is one process and every function here is what one process does (`gather` returns [its input]).

Shares are contiguous: process p of P takes the p-th of P consecutive runs of the items (`split`), so the shares
gathered in process order are the items in their order, whatever P is."""
from __future__ import annotations

import os

import numpy as np

ENV_COORDINATOR = "GSP_JAX_COORDINATOR"  # host:port of process 0's coordinator service
ENV_NUM_PROCESSES = "GSP_JAX_NUM_PROCESSES"
ENV_PROCESS_ID = "GSP_JAX_PROCESS_ID"
INIT_TIMEOUT_S = 120  # [s] every process must have joined by then, or each one stops with an error
HEARTBEAT_TIMEOUT_S = 30  # [s] a process silent this long (killed, crashed) ends the others' runs with an error
SHUTDOWN_TIMEOUT_S = 24 * 3600  # [s] a finished process waits this long at exit for the others (process 0 writes
# the results after the last gather: the others wait for it, not the reverse)

BATCH_AXIS = "batch"  # the mesh axis of `over_local_devices`
PIECE_BYTES = 1 << 20  # [bytes] `gather` moves a value through the runtime's key-value store in pieces of this size
BARRIER_TIMEOUT_S = 24 * 3600  # [s] the longest a process waits for the others at a barrier (one shard's work)

_started = False
_calls: dict[str, int] = {}  # name -> barriers of that name passed


class DistributedError(RuntimeError):
    """The runtime could not start, or the environment's settings are inconsistent; the message names them."""


def requested() -> bool:
    """Whether this process's environment asks for several processes (ours, Slurm's or Open MPI's)."""
    if ENV_COORDINATOR in os.environ:
        return True
    if int(os.environ.get("SLURM_NTASKS", "1") or 1) > 1 and "SLURM_STEP_ID" in os.environ:
        return True
    return int(os.environ.get("OMPI_COMM_WORLD_SIZE", "1") or 1) > 1


def initialize() -> bool:
    """Start JAX's distributed runtime where the environment asks for it (`requested`), once; before any other JAX
    call of the process. True where this process is one of several."""
    global _started
    if _started:
        return True
    if not requested():
        return False
    import jax

    kwargs = dict(initialization_timeout=INIT_TIMEOUT_S, heartbeat_timeout_seconds=HEARTBEAT_TIMEOUT_S,
                  shutdown_timeout_seconds=SHUTDOWN_TIMEOUT_S)
    if ENV_COORDINATOR in os.environ:
        try:
            n, rank = int(os.environ[ENV_NUM_PROCESSES]), int(os.environ[ENV_PROCESS_ID])
        except (KeyError, ValueError) as e:
            raise DistributedError(f"{ENV_COORDINATOR} is set, so {ENV_NUM_PROCESSES} and {ENV_PROCESS_ID} must be "
                                   f"integers: got {os.environ.get(ENV_NUM_PROCESSES)!r} and "
                                   f"{os.environ.get(ENV_PROCESS_ID)!r}") from e
        if not (n >= 1 and 0 <= rank < n):
            raise DistributedError(f"{ENV_PROCESS_ID}={rank} is not one of the {ENV_NUM_PROCESSES}={n} processes")
        kwargs.update(coordinator_address=os.environ[ENV_COORDINATOR], num_processes=n, process_id=rank)
    try:
        jax.distributed.initialize(**kwargs)
    except Exception as e:  # the runtime's own message (timeouts, an unreachable coordinator) with where it failed
        raise DistributedError(f"process {os.environ.get(ENV_PROCESS_ID, '?')}: JAX's distributed runtime did not "
                               f"start: {type(e).__name__}: {e}") from e
    _started = True
    return True


def rank() -> int:
    """This process's index, 0 .. count() - 1 (0 for one process)."""
    if not _started:
        return 0
    import jax

    return jax.process_index()


def count() -> int:
    """The number of processes of the run (1 for one process)."""
    if not _started:
        return 1
    import jax

    return jax.process_count()


def is_main() -> bool:
    """Process 0: the one that writes results and records."""
    return rank() == 0


def split(n: int, parts: int | None = None) -> list[range]:
    """The contiguous share of each of `parts` processes (default `count()`) of n items, in process order: the
    first n % parts shares one item longer. Shares may be empty (more processes than items)."""
    parts = count() if parts is None else parts
    if parts < 1 or n < 0:
        raise ValueError(f"split: needs n >= 0 and parts >= 1, got n={n}, parts={parts}")
    base, extra = divmod(n, parts)
    bounds = np.cumsum([0] + [base + (p < extra) for p in range(parts)])
    return [range(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]


def chunks(n: int, size: int) -> list[np.ndarray]:
    """The item indices of each fixed chunk, (size,) int: consecutive runs of `size` of the `n` items, the last one
    shorter. A chunk is the unit of work whatever the process count: each one runs the same program on the same
    inputs in one process or in several, so the gathered results are one process's, bit for bit."""
    if size < 1 or n < 0:
        raise ValueError(f"chunks: needs n >= 0 and size >= 1, got n={n}, size={size}")
    return [np.arange(i, min(i + size, n)) for i in range(0, n, size)]


def chunk_size(n: int, size: int | None = None) -> int:
    """`size` items a chunk, or where None one chunk per process: ceil(n / count()). ValueError below 1."""
    size = -(-n // count()) if size is None else size
    if size < 1:
        raise ValueError(f"chunk (--chunk) must be >= 1, got {size}")
    return size


def share(n: int) -> range:
    """This process's contiguous share of n items (`split`): all of them for one process."""
    return split(n)[rank()]


def gather(obj) -> list:
    """Every process's `obj` (anything pickle writes: numpy arrays travel bit for bit), in process order, on every
    process; [obj] for one process. Every process must call it, in the same order. The bytes go through the
    runtime's key-value store (in pieces of `PIECE_BYTES`), not through device collectives: this works on any
    platform, and where several processes share one GPU (which NCCL refuses)."""
    if count() == 1:
        return [obj]
    import pickle

    client = _client()
    _calls["gather/values"] = call = _calls.get("gather/values", 0) + 1
    raw = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    mine = f"gsp_jax/gather/{call}/{rank()}"
    pieces = range(0, max(len(raw), 1), PIECE_BYTES)
    for i, start in enumerate(pieces):
        client.key_value_set_bytes(f"{mine}/{i}", raw[start:start + PIECE_BYTES])
    client.key_value_set(f"{mine}/pieces", str(len(pieces)))  # last: a reader that sees it finds every piece
    wait = BARRIER_TIMEOUT_S * 1000
    out = []
    for p in range(count()):
        key = f"gsp_jax/gather/{call}/{p}"
        n = int(client.blocking_key_value_get(f"{key}/pieces", wait))
        out.append(pickle.loads(b"".join(client.blocking_key_value_get_bytes(f"{key}/{i}", wait) for i in range(n))))
    barrier("gather")  # every process has read every piece: each removes its own
    for i in range(len(pieces)):
        client.key_value_delete(f"{mine}/{i}")
    client.key_value_delete(f"{mine}/pieces")
    return out


def gather_joined(mine: list) -> list:
    """Every process's list, joined in process order (`gather`): with contiguous shares, the whole list in order."""
    return [item for part in gather(mine) for item in part]


def gather_merged(mine: dict) -> dict:
    """Every process's dict merged into one (`gather`; the processes' keys are apart, e.g. their chunks' indices)."""
    return {key: value for part in gather(mine) for key, value in part.items()}


def map_chunks(fn, n: int, size: int, shared: bool = True, what: str = "items"):
    """`fn(idx)` over the fixed chunks of n items (`chunks`), joined along every leaf's first axis in chunk order:
    `fn(idx)` gives a pytree whose leaves are arrays (len(idx), ...) (numpy: they are gathered). With several
    processes (`shared`) each runs its share of the chunks (`share`) and every process gets the whole (`gather`):
    each chunk runs the same program on the same inputs, so the result is one process's, bit for bit. `what` names
    the items in the line each process prints."""
    import jax

    if n < 1:
        raise ValueError(f"map_chunks: needs n >= 1 items, got {n}")
    pieces = chunks(n, size)
    mine = share(len(pieces)) if shared else range(len(pieces))
    if shared and count() > 1:
        print(f"  process {rank()} of {count()} runs chunks {mine.start + 1}-{mine.stop} of {len(pieces)} "
              f"({size} {what} each)", flush=True)
    done = {c: jax.tree.map(np.asarray, fn(pieces[c])) for c in mine}
    if shared:
        done = gather_merged(done)
    return jax.tree.map(lambda *xs: np.concatenate(xs), *(done[c] for c in range(len(pieces))))


def _client():
    """The distributed runtime's client (its key-value store and barriers)."""
    from jax._src import distributed as jax_distributed

    return jax_distributed.global_state.client


def barrier(name: str) -> None:
    """Wait until every process has reached its barrier of this name (the n-th call of a name meets the others'
    n-th), for up to `BARRIER_TIMEOUT_S`; a process that dies meanwhile ends the wait with an error (the runtime's
    heartbeat). Nothing for one process."""
    if count() == 1:
        return
    _calls[name] = _calls.get(name, 0) + 1
    _client().wait_at_barrier(f"gsp_jax/{name}/{_calls[name]}", BARRIER_TIMEOUT_S * 1000)  # a timeout of ours


def total(value: float) -> float:
    """The sum of every process's `value`, on every process."""
    return float(sum(gather(float(value))))


def over_local_devices(fn):
    """`fn(*args, batch)` jitted, its batch (the last argument, leaves (N, ...)) split over every local device: each
    of the D devices runs `fn` on ceil(N / D) consecutive elements (the batch padded with copies of its last
    element, which are cut off after), the other arguments on every device. `fn` must treat each element of its
    batch alone (a vmap) and give leaves (N, ...). With one device this is `jax.jit(fn)`."""
    import jax
    import jax.numpy as jnp
    from jax.sharding import Mesh, PartitionSpec

    devices = jax.local_devices()
    if len(devices) == 1:
        return jax.jit(fn)
    mesh = Mesh(np.array(devices), (BATCH_AXIS,))

    def split(*args):
        *rest, batch = args
        n = jax.tree.leaves(batch)[0].shape[0]
        pad = -n % len(devices)
        batch = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), batch)
        # no collectives: each device's elements alone (so no check that constant scan carries vary by device)
        out = jax.shard_map(fn, mesh=mesh, in_specs=(*[PartitionSpec()] * len(rest), PartitionSpec(BATCH_AXIS)),
                            out_specs=PartitionSpec(BATCH_AXIS), check_vma=False)(*rest, batch)
        return jax.tree.map(lambda x: x[:n], out)

    return jax.jit(split)
