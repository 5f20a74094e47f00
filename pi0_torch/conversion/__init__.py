"""Checkpoint conversion: openpi (orbax, read without JAX), LeRobot and transformers folders to pi0-torch, and back."""

from pi0_torch.conversion.convert import (
    ConversionError,
    ConversionResult,
    convert_hf_checkpoint,
    convert_openpi_checkpoint,
    export_to_transformers,
)

__all__ = ["ConversionError", "ConversionResult", "convert_hf_checkpoint", "convert_openpi_checkpoint", "export_to_transformers"]
