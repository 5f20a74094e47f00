"""Count the ATen operations a piece of code runs: a CPU-side proxy for the kernel launches it costs on a GPU.

```python
>>> import torch
>>> with AtenOpCounter() as counter:
...     x = torch.ones(4, 4)
...     y = (x @ x.t()).sum()
>>> counter.total, counter.views, counter.host_reads
(4, 1, 0)
>>> with AtenOpCounter() as counter:
...     _ = bool(torch.ones(2).sum() > 1)  # the host waits for a value
>>> counter.host_reads
1

```

Every op counts, views included (they launch nothing on a GPU, `views` tells how many there were). Ops that run as
one kernel on CUDA but as their decomposition on the CPU (RMSNorm's `_fused_rms_norm`) count as those parts. Host
reads are the ops that copy a device value to the host for Python to look at (`.item()`, `bool(tensor)`, `nonzero`);
on a GPU each one waits for all queued work. (`.tolist()` / `.cpu()` of a CPU tensor dispatch nothing and are not seen.)
"""

from __future__ import annotations

from collections import Counter
from typing import Any

from torch.utils._python_dispatch import TorchDispatchMode

HOST_READS = frozenset({"_local_scalar_dense", "nonzero", "equal"})


class AtenOpCounter(TorchDispatchMode):
    """A dispatch mode that counts every ATen op run inside it, by name (`ops`)."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()
        self.views = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        self.ops[func.overloadpacket.__name__] += 1
        self.views += func.is_view
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.ops.values())

    @property
    def host_reads(self) -> int:
        return sum(count for name, count in self.ops.items() if name in HOST_READS)
