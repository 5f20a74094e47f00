"""Checkpoint conversion: openpi (orbax, read without JAX), LeRobot and transformers folders to pi0-torch, and back
(imported on first use)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.conversion.convert_hf import convert_hf_checkpoint, export_to_transformers
    from pi0_torch.conversion.convert_openpi import convert_openpi_checkpoint
    from pi0_torch.conversion.output_folder import ConversionError, ConversionResult

_EXPORTS = {
    "ConversionError": "pi0_torch.conversion.output_folder",
    "ConversionResult": "pi0_torch.conversion.output_folder",
    "convert_hf_checkpoint": "pi0_torch.conversion.convert_hf",
    "convert_openpi_checkpoint": "pi0_torch.conversion.convert_openpi",
    "export_to_transformers": "pi0_torch.conversion.convert_hf",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
