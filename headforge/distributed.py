"""Data-parallel training over processes with ``torch.distributed`` (launched by ``torchrun``).

The scheme every trainer here uses (the avatar engine; meant for the HeadCraft generator too):

- every rank holds the whole model and draws the same global batches from the same seeded
  generator; :func:`shard` gives each rank its contiguous share of a global batch;
- after ``backward`` :func:`average_gradients` averages every parameter's gradient over the
  ranks (one all-reduce of a flat buffer; the gradient of a loss that is a mean over the
  batch's items is then exactly the single-process gradient of the global batch). Parameters
  that belong to items (a frame's expression and pose) get a gradient only on the rank that
  holds the item, so the average carries the owner's gradient (divided by the world size, as
  the single-process mean over the global batch does) to every rank: every rank's copy of
  every parameter stays identical, and rank 0's checkpoint is complete;
- :func:`merge_rows` gathers per-item work done on one rank each (per-frame fitting);
- only :func:`is_main` (rank 0) writes files and logs.

Without an initialised process group every function is a no-op (one rank), so a trainer's
single-process path is the same code. Backends: gloo on the CPU, NCCL on CUDA
(:func:`init_from_environment` picks by device). This is DistributedDataParallel's
arithmetic written out: the avatar methods render through their own calls, not through
``module.forward``, which DDP's hooks need.
"""

from __future__ import annotations

import datetime
import os

import torch
import torch.distributed as dist

from headforge.errors import HeadforgeError

TIMEOUT = datetime.timedelta(hours=2)  # rank 0 scores and writes while the others wait at the next collective


def active() -> bool:
    """True inside an initialised process group of more than one rank."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def rank() -> int:
    return dist.get_rank() if active() else 0


def world_size() -> int:
    return dist.get_world_size() if active() else 1


def is_main() -> bool:
    """Rank 0 (or the only process): the one that writes files and logs."""
    return rank() == 0


def launched() -> bool:
    """True when this process was started by ``torchrun`` (or another launcher that sets
    ``WORLD_SIZE``) with more than one process."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init_from_environment(device: str = "auto") -> torch.device:
    """Join the process group ``torchrun`` describes in the environment (RANK, WORLD_SIZE,
    LOCAL_RANK, MASTER_ADDR/PORT) and return this rank's device: ``auto`` -> ``cuda:LOCAL_RANK``
    when CUDA is available, else the CPU; ``cuda`` -> ``cuda:LOCAL_RANK``; ``cpu``. NCCL on
    CUDA, gloo on the CPU. Without a launcher: no group, the device as asked."""
    from headforge.devices import limit_threads, resolve_device

    if not launched():
        return resolve_device(device)
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device in ("auto", "cuda"):
        if torch.cuda.is_available():
            if local >= torch.cuda.device_count():
                raise HeadforgeError(f"rank with LOCAL_RANK {local} has no GPU: {torch.cuda.device_count()} here "
                                     "(start as many processes per node as GPUs)")
            target = torch.device("cuda", local)
        elif device == "cuda":
            raise HeadforgeError("--device cuda: PyTorch sees no CUDA GPU here")
        else:
            target = torch.device("cpu")
    else:
        target = resolve_device(device)
    if target.type == "cuda":
        torch.cuda.set_device(target)
    else:  # torchrun sets OMP_NUM_THREADS per process; numba would still take every core in each
        limit_threads(torch.get_num_threads())
    if not dist.is_initialized():
        dist.init_process_group("nccl" if target.type == "cuda" else "gloo", timeout=TIMEOUT,
                                device_id=target if target.type == "cuda" else None)
    return target


def shutdown() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def barrier() -> None:
    if active():
        dist.barrier()


def shard(rows: torch.Tensor) -> torch.Tensor:
    """This rank's contiguous share of a global batch ``rows`` (its length a multiple of the
    world size, so every share is the same size and the mean of the shares' means is the
    batch's mean)."""
    if not active():
        return rows
    n = world_size()
    if len(rows) % n:
        raise HeadforgeError(f"a batch of {len(rows)} cannot be split evenly over {n} processes: "
                             f"use a batch size that is a multiple of {n}")
    return rows.tensor_split(n)[rank()]


def average_gradients(parameters) -> None:
    """Average the gradients of ``parameters`` (the same list, in the same order, on every
    rank) over the ranks, in place. A parameter whose gradient is None on some ranks and not
    on others gets zeros there first (it is used by another rank's items only); one that has
    none anywhere keeps None (an optimiser then skips it, as in a single process)."""
    if not active():
        return
    params = [p for p in parameters if p.requires_grad]
    if not params:
        return
    device = params[0].device
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.float32, device=device)
    dist.all_reduce(has)
    used = [p for p, h in zip(params, has.tolist()) if h > 0]
    if not used:
        return
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).reshape(-1) for p in used])
    dist.all_reduce(flat)
    flat /= world_size()
    offset = 0
    for p in used:
        n = p.numel()
        p.grad = flat[offset:offset + n].view_as(p).clone()
        offset += n


def combine_flags(module: torch.nn.Module) -> None:
    """OR every boolean buffer of ``module`` over the ranks: flags a rank sets from the items it
    saw (PointAvatar's point visibility, which pruning reads) must be the union of all items."""
    if not active():
        return
    for buffer in (b for _, b in module.named_buffers() if b.dtype == torch.bool):
        flags = buffer.to(torch.uint8)
        dist.all_reduce(flags, op=dist.ReduceOp.MAX)
        buffer.copy_(flags.bool())


def mean_terms(terms: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The ranks' mean of each (scalar) term of ``terms`` (detached; the same keys on every
    rank): the global batch's figures for the logs."""
    if not active() or not terms:
        return terms
    values = torch.stack([v.detach().reshape(()) for v in terms.values()])
    dist.all_reduce(values)
    values /= world_size()
    return dict(zip(terms, values))


def owned(n_items: int) -> list[int]:
    """The items among ``0..n_items-1`` this rank works on when each item goes to one rank
    (round robin)."""
    return list(range(rank(), n_items, world_size()))


def merge_rows(tables: dict[str, torch.Tensor], rows: torch.Tensor, mine: torch.Tensor) -> None:
    """After each rank updated its own rows of ``tables`` (name -> (T, ...) tensors, e.g. the
    per-frame parameters): give every rank the owner's values of ``rows`` (N,) long, ``mine``
    (N,) bool marking the rows this rank owns (each row owned by exactly one rank). In place;
    one all-reduce (a sum over ranks in which only the owner's value is non-zero)."""
    if not active() or len(rows) == 0:
        return
    with torch.no_grad():
        keys = list(tables)
        parts = [tables[k][rows].reshape(len(rows), -1) for k in keys]
        flat = torch.where(mine.to(parts[0].device)[:, None], torch.cat(parts, 1), 0.0)
        dist.all_reduce(flat)
        offset = 0
        for k, part in zip(keys, parts):
            width = part.shape[1]
            tables[k][rows] = flat[:, offset:offset + width].reshape(tables[k][rows].shape).to(tables[k].dtype)
            offset += width


def broadcast_object(obj):
    """Rank 0's ``obj`` (picklable) on every rank."""
    if not active():
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]
