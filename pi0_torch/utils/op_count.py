"""Count the ATen operations a piece of code runs: a CPU-side proxy for the kernel launches it costs on a GPU.

```python
>>> import torch
>>> with AtenOpCounter() as counter:
...     x = torch.ones(4, 4)
...     y = (x @ x.t()).sum()
>>> counter.total, counter.views, counter.kernels, counter.host_reads
(4, 1, 3, 0)
>>> with AtenOpCounter() as counter:
...     _ = bool(torch.ones(2).sum() > 1)  # the host waits for a value
>>> counter.host_reads
1
>>> with AtenOpCounter() as counter:
...     _ = torch.ones(2).to("meta")  # a host tensor copied to a device
>>> counter.host_copies
1
>>> x = torch.ones(2, 8)
>>> with AtenOpCounter() as counter:  # one op on a CUDA build, its decomposition on the CPU
...     _ = torch.ops.aten._fused_rms_norm(x, [8], None, 1e-6)
>>> counter.ops["_fused_rms_norm"], counter.total, counter.dispatched > 1
(1, 1, True)
>>> q = torch.ones(1, 2, 4, 8)  # [B, heads, T, H]
>>> with AtenOpCounter() as counter:  # the heads put back together: a view of what CUDA's attention kernels write
...     _ = torch.nn.functional.scaled_dot_product_attention(q, q, q).transpose(1, 2).reshape(1, 4, 16)
>>> counter.kernels
1

```

Every op counts, views and allocations included (they launch nothing on a GPU: `views` and `allocations` tell how many
there were, `kernels` the rest). `_unsafe_view` (what `reshape` returns after its copy) and `lift_fresh` (a constant
tensor entering the program) change no memory either and count as views.
The calls in `ONE_OP_ON_CUDA` run as one kernel on CUDA (RMSNorm's `_fused_rms_norm`; `scaled_dot_product_attention`,
one flash / efficient / cuDNN kernel there) but as several ops elsewhere (their decomposition on the CPU or `meta`, the
math kernel on `meta`): each call counts as one op, and `dispatched` counts the ops as they ran here instead. An
attention's output `[B, N, T, H]` comes back laid out as those CUDA kernels write it, `[B, T, N, H]` in memory (the
math kernel writes `[B, N, T, H]`), so that putting the heads back together (`transpose(1, 2).reshape(B, T, N * H)`)
counts the copy CUDA runs: none.

Host reads are the ops that copy a device value to the host for Python to look at (`.item()`, `bool(tensor)`, `nonzero`);
on a GPU each one waits for all queued work. Host copies are the ops that copy a host tensor (not a 0-dim scalar) to
another device: inside a CUDA graph one would be replayed from the host memory it saw at capture, or refused when that
memory is not pinned. (`.tolist()` / `.cpu()` of a CPU tensor dispatch nothing and are not seen, nor is work a
backend kernel does inside one op: CUDA's out-of-place `addmm` copies its input first.)
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten
from torch.utils._python_dispatch import TorchDispatchMode

HOST_READS = frozenset({"_local_scalar_dense", "nonzero", "equal"})
ALLOCATIONS = frozenset({"empty", "empty_strided", "new_empty", "new_empty_strided"})  # memory, no kernel
ONE_OP_ON_CUDA = frozenset({"_fused_rms_norm", "scaled_dot_product_attention"})
UNRECORDED_VIEWS = frozenset({"_unsafe_view", "lift_fresh"})  # no memory touched, though not marked as views


class AtenOpCounter(TorchDispatchMode):
    """A dispatch mode that counts every ATen op run inside it, by name (`ops`); see the module docstring."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()
        self.views = 0
        self.allocations = 0
        self.decomposed = 0
        self.host_copies = 0
        self._inside_one_op = False
        self._calls = _OneOpCalls(self)

    def __enter__(self) -> AtenOpCounter:
        self._calls.__enter__()
        return super().__enter__()

    def __exit__(self, *exc: Any) -> None:
        super().__exit__(*exc)
        self._calls.__exit__(*exc)

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        if self._inside_one_op:  # what an op counted where it was called runs as here
            self.decomposed += 1
        else:
            name = func.overloadpacket.__name__
            self.ops[name] += 1
            self.views += func.is_view or name in UNRECORDED_VIEWS
            self.allocations += name in ALLOCATIONS
        result = func(*args, **(kwargs or {}))
        if not self._inside_one_op:
            self.host_copies += _copies_from_host(args, kwargs, result)
        return result

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def kernels(self) -> int:
        """The ops that launch work on a GPU: neither views nor allocations."""
        return self.total - self.views - self.allocations

    @property
    def dispatched(self) -> int:
        """The ops as this device ran them: each `ONE_OP_ON_CUDA` call as the ops it took here."""
        return self.total - sum(self.ops[name] for name in ONE_OP_ON_CUDA) + self.decomposed

    @property
    def host_reads(self) -> int:
        return sum(count for name, count in self.ops.items() if name in HOST_READS)


def _copies_from_host(args: tuple, kwargs: dict | None, result: Any) -> bool:
    """Whether an op read a host tensor (not a 0-dim scalar, which kernels take by value) into another device's."""
    tensors = [value for value in tree_flatten((args, kwargs))[0] if isinstance(value, torch.Tensor)]
    if not any(tensor.device.type == "cpu" and tensor.dim() > 0 for tensor in tensors):
        return False
    return any(isinstance(value, torch.Tensor) and value.device.type != "cpu" for value in tree_flatten(result)[0])


class _OneOpCalls(TorchFunctionMode):
    """Sees the calls of `ONE_OP_ON_CUDA` ops before they decompose, and counts each as one op."""

    def __init__(self, counter: AtenOpCounter) -> None:
        super().__init__()
        self.counter = counter

    def __torch_function__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        name = getattr(func, "__name__", "").split(".")[0]
        if name not in ONE_OP_ON_CUDA:
            return func(*args, **(kwargs or {}))
        self.counter.ops[name] += 1
        self.counter._inside_one_op = True
        try:
            result = func(*args, **(kwargs or {}))
            if name == "scaled_dot_product_attention" and result.dim() == 4:  # CUDA's layout (see the module docstring)
                result = result.transpose(1, 2).contiguous().transpose(1, 2)
            return result
        finally:
            self.counter._inside_one_op = False
