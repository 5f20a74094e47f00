"""The inference settings a policy was validated with, kept beside its weights: `policy_settings.json`.

A policy's success can hang on how it is run: the demo policy succeeds on Conveyor 88-94% of the time with noise of
standard deviation 0.1 and 4 actions executed per chunk, and 38% with the defaults (1.0 and the whole chunk). A model
folder therefore holds the settings it should run with, and `PI0Policy.from_pretrained`, `pi0-torch eval` and
`pi0-torch serve` use them unless told otherwise, saying which they use:

```json
{"noise_scale": 0.1, "replan_steps": 4}
```

- `noise_scale`: the standard deviation of the noise each chunk's flow starts from (`PI0Policy(noise_scale=...)`);
- `replan_steps`: actions to execute per chunk before the next observation (`pi0-torch eval --replan-steps`; a
  server's clients find it in the metadata);
- `rtc_method`: the real-time chunking method for continued chunks ("guidance" or "conditioning");
- `num_steps`: Euler steps per chunk;
- `max_abs_action`: the largest |action| in the robot's units that leaves the policy; a chunk with a larger value is
  withheld (`UnsafeActionsError`), as a chunk with NaN is. None: no bound in robot units (every policy with norm stats
  still withholds a chunk beyond ±1000 in its normalized space, `action_safety.MAX_NORMALIZED_ACTION`).

Write one by hand or with `PolicySettings(noise_scale=0.1, replan_steps=4).save(folder)`; `pi0-torch train` carries
the base model's file over to a fine-tuned one.

>>> import tempfile
>>> folder = tempfile.mkdtemp()
>>> PolicySettings(noise_scale=0.1, replan_steps=4).save(folder)
>>> PolicySettings.load(folder)
PolicySettings(noise_scale=0.1, replan_steps=4, rtc_method=None, num_steps=None, max_abs_action=None)
>>> PolicySettings.load(folder).describe()
'noise_scale 0.1, replan_steps 4'
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from pi0_torch.utils import files
from pi0_torch.utils.validation import check_float, check_int, read_json_file

SETTINGS_FILE = "policy_settings.json"
RTC_METHODS = ("guidance", "conditioning")  # (pi0_torch.inference.rtc.METHODS, without importing torch here)
MAX_NOISE_SCALE = 10.0  # every policy's bound: ten times the training noise (1e30 gave NaN actions)
MAX_STEPS = 8192
MAX_ABS_ACTION = float(2**24)  # (the norm stats' own bound, `normalization.MAX_STATISTIC`)


@dataclasses.dataclass(frozen=True)
class PolicySettings:
    """Recommended inference settings of one model folder (None: the caller's default)."""

    noise_scale: float | None = None
    replan_steps: int | None = None
    rtc_method: str | None = None
    num_steps: int | None = None
    max_abs_action: float | None = None

    def __post_init__(self) -> None:
        where = SETTINGS_FILE
        if self.noise_scale is not None:
            check_float(f"{where}: noise_scale", self.noise_scale, minimum=0.0, maximum=MAX_NOISE_SCALE)
        if self.replan_steps is not None:
            check_int(f"{where}: replan_steps", self.replan_steps, minimum=1, maximum=MAX_STEPS)
        if self.num_steps is not None:
            check_int(f"{where}: num_steps", self.num_steps, minimum=1, maximum=MAX_STEPS)
        if self.max_abs_action is not None:
            check_float(f"{where}: max_abs_action", self.max_abs_action, minimum=0.0, maximum=MAX_ABS_ACTION)
        if self.rtc_method is not None and self.rtc_method not in RTC_METHODS:
            raise ValueError(f"{where}: rtc_method must be one of {RTC_METHODS}, got {self.rtc_method!r:.60}")

    @classmethod
    def load(cls, folder: str | Path) -> PolicySettings:
        """The folder's settings (all None when it has no `policy_settings.json`); a malformed file is a `ValueError`
        naming it and the field."""
        path = Path(folder) / SETTINGS_FILE
        if not path.exists() and not path.is_symlink():
            return cls()
        values = read_json_file(path)  # (a folder, a device or a dangling link there is refused, not skipped)
        if not isinstance(values, dict):
            raise ValueError(f"{path}: expected a JSON object of settings, got a JSON {type(values).__name__}")
        unknown = sorted(set(values) - {field.name for field in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"{path}: unknown settings {unknown}; known: {[f.name for f in dataclasses.fields(cls)]}")
        return cls(**values)

    def save(self, folder: str | Path) -> None:
        """Write `policy_settings.json` into `folder` (the set fields only; whole or not at all)."""
        values = {key: value for key, value in dataclasses.asdict(self).items() if value is not None}
        files.write_text_atomically(Path(folder) / SETTINGS_FILE, json.dumps(values, indent=2) + "\n")

    def describe(self) -> str:
        """`noise_scale 0.1, replan_steps 4`: the set fields, for a log line."""
        return ", ".join(f"{key} {value}" for key, value in dataclasses.asdict(self).items() if value is not None)

    def resolve(self, **given: Any) -> dict[str, Any]:
        """`given` (a caller's arguments, None where not given) with each None filled from these settings."""
        return {key: self_value if value is None and (self_value := getattr(self, key)) is not None else value
                for key, value in given.items()}
