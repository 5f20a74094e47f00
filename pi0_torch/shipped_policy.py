"""The demo policy shipped inside the package (`pi0_torch/demo_policy/`): where it is, wherever the package is
installed ([`demo_policy_dir`], `pi0_torch.demo_policy_dir()`), and the name `demo` that `pi0-torch eval --policy`,
`serve --model` and `demo --policy` accept for it ([`policy_location`]).

How the policy was trained is `scripts/train_demo_policy.py`; how it acts, `pi0_torch.demo` (`pi0-torch demo`).
"""

from __future__ import annotations

from pathlib import Path

DEMO_POLICY_NAME = "demo"  # what `--policy` / `--model` of eval, serve and demo accept for the shipped policy


def demo_policy_dir() -> Path:
    """The folder of the demo policy shipped inside the package, wherever it is installed.

    >>> sorted(p.name for p in demo_policy_dir().glob("*.json"))
    ['config.json', 'demo_metrics.json', 'norm_stats.json', 'policy_settings.json', 'processor_config.json']
    """
    return Path(__file__).resolve().parent / "demo_policy"


def policy_location(name_or_path: str | Path) -> str | Path:
    """A `--policy` / `--model` value as a location: `demo` is [`demo_policy_dir`], anything else is itself (a
    folder named `demo` in the working directory is `./demo`)."""
    return demo_policy_dir() if str(name_or_path) == DEMO_POLICY_NAME else name_or_path
