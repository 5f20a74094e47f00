"""Library calls are quiet: transformers' progress bars ("Loading weights", "Writing model shards") only when asked.

transformers draws those bars through `transformers.utils.logging.tqdm`, which checks a process-wide switch each
time a bar is made. [`transformers_progress`] sets that switch for the duration of one call and puts back what it
was, so a user who turned the bars on or off for their own code keeps that setting.

```python
>>> from transformers.utils import logging as hf_logging
>>> before = hf_logging.is_progress_bar_enabled()
>>> with transformers_progress(False):
...     hf_logging.is_progress_bar_enabled()
False
>>> hf_logging.is_progress_bar_enabled() == before
True

```
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from transformers.utils import logging as hf_logging


@contextmanager
def transformers_progress(enabled: bool) -> Iterator[None]:
    """Within the block transformers shows its progress bars only when `enabled`; the previous setting returns after."""
    was_enabled = hf_logging.is_progress_bar_enabled()
    if enabled != was_enabled:
        (hf_logging.enable_progress_bar if enabled else hf_logging.disable_progress_bar)()
    try:
        yield
    finally:
        if enabled != was_enabled:
            (hf_logging.enable_progress_bar if was_enabled else hf_logging.disable_progress_bar)()
