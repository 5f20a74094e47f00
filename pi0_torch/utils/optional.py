"""Type checks for values of libraries a module needs only for some inputs. The processing code runs without torch,
transformers or huggingface_hub in a torch-free install (an exported policy run by onnxruntime, `pi0_torch.deploy`), so
it asks here instead of importing them: a value can only be a torch tensor once torch is imported."""

from __future__ import annotations

import sys
from typing import Any


def is_torch_tensor(value: Any) -> bool:
    """Whether `value` is a `torch.Tensor` (never imports torch: where it is not imported, nothing is one)."""
    torch = sys.modules.get("torch")
    return torch is not None and isinstance(value, getattr(torch, "Tensor", ()))


def is_transformers_tokenizer(value: Any) -> bool:
    """Whether `value` is a transformers tokenizer (`PreTrainedTokenizerBase`; never imports transformers)."""
    if "transformers" not in sys.modules:
        return False
    from transformers import PreTrainedTokenizerBase

    return isinstance(value, PreTrainedTokenizerBase)
