"""The progress bar of every command and notebook: tqdm's notebook widget where ipywidgets is installed, else its text
bar. (`tqdm.auto` in a notebook without ipywidgets warns "IProgress not found. Please update jupyter and ipywidgets"
before falling back to the text bar; ipywidgets is no dependency of pi0-torch.)"""

from __future__ import annotations

import importlib.util

if importlib.util.find_spec("ipywidgets") is not None:
    from tqdm.auto import tqdm
else:
    from tqdm.std import tqdm

__all__ = ["tqdm"]
