"""Distributed helpers, below train/ and infer/ (both use them): torchrun environment -> process group
(gloo on CPU, nccl on CUDA), or one process.

`torchrun --nproc_per_node N -m cli.fastocc_cli train ...` sets RANK / WORLD_SIZE / LOCAL_RANK and the
rendezvous address; multi-node runs use torchrun's `--nnodes`, `--node_rank` / `--rdzv_endpoint`
(docs/training.md). Without those variables everything runs in one process and the helpers are no-ops.
"""

from __future__ import annotations

import contextlib
import datetime
import os
from collections.abc import Iterator
from dataclasses import dataclass

import torch
import torch.distributed as dist

from occdata.errors import OccDataError

__all__ = ["CollectiveError", "DistInfo", "all_reduce_sum", "any_rank", "barrier", "broadcast_object",
           "collective_errors", "resolve_device", "setup", "teardown"]


class CollectiveError(OccDataError):
    """A collective operation timed out or lost a peer (one line instead of a hang or a C++ traceback)."""


@dataclass(frozen=True)
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: torch.device = torch.device("cpu")

    @property
    def enabled(self) -> bool:
        return self.world_size > 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def resolve_device(device: str) -> str:
    """`--device auto` is "cuda" when a CUDA device is available, else "cpu"; any other name as given."""
    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return device


def setup(device: str, timeout_s: float = 1800.0) -> DistInfo:
    """Resolve the device ("auto" = cuda when available) and join the process group when under torchrun.

    `timeout_s`: how long a collective waits for the other processes before it fails (`collective_errors`
    turns that failure into one line)."""
    device = resolve_device(device)
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if device == "cuda":
        if not torch.cuda.is_available():
            raise OccDataError("--device cuda but no CUDA device is available (use --device cpu)")
        torch.cuda.set_device(local)
        dev = torch.device("cuda", local)
    else:
        dev = torch.device("cpu")
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if dev.type == "cuda" else "gloo",
                                timeout=datetime.timedelta(seconds=timeout_s))
    return DistInfo(rank=rank, world_size=world, local_rank=local, device=dev)


def teardown(info: DistInfo) -> None:
    if info.enabled and dist.is_initialized():
        dist.destroy_process_group()


def barrier(info: DistInfo) -> None:
    if info.enabled:
        dist.barrier()


def all_reduce_sum(values: torch.Tensor, info: DistInfo) -> torch.Tensor:
    """Sum a tensor over ranks (in place on a copy); identity in one process."""
    if not info.enabled:
        return values
    out = values.detach().clone().to(info.device)
    dist.all_reduce(out, op=dist.ReduceOp.SUM)
    return out.cpu()


def broadcast_object(obj: object, info: DistInfo) -> object:
    """Rank 0's object on every rank."""
    if not info.enabled:
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=0)
    return box[0]


def gather_ints(value: int, info: DistInfo) -> tuple[int, ...]:
    """Every rank's `value`, in rank order, on every rank (`(value,)` in one process)."""
    if not info.enabled:
        return (int(value),)
    out: list[object] = [None] * info.world_size
    torch.distributed.all_gather_object(out, int(value))
    return tuple(int(v) for v in out)  # type: ignore[arg-type]


def any_rank(flag: bool, info: DistInfo) -> bool:
    """True on every rank when `flag` is True on at least one (all ranks must call it at the same point)."""
    if not info.enabled:
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=info.device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item() > 0)


_PEER_LOST = ("timed out", "timeout", "connection closed", "connection reset", "broken pipe", "socket closed")


@contextlib.contextmanager
def collective_errors(info: DistInfo) -> Iterator[None]:
    """Re-raise a collective's timeout or lost peer (gloo/NCCL RuntimeError) as one `CollectiveError` line."""
    try:
        yield
    except RuntimeError as exc:
        text = str(exc)
        if not info.enabled or not any(s in text.lower() for s in _PEER_LOST):
            raise
        first = next((ln.strip() for ln in text.splitlines() if ln.strip()), text)[:200]
        raise CollectiveError(f"rank {info.rank}: a collective operation with the other processes failed ({first}); "
                              "another process stopped or hung. Its own output says why; the run can continue "
                              "from last.pt with --resume") from None
