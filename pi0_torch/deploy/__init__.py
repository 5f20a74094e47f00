"""Running a policy where the robot is: `pi0-torch export` writes a π0 / π0.5 model as one verified graph (ONNX, or an
AOTInductor package) with what its inputs need (`pi0_torch.deploy.folder`), and `ExportedPolicy` runs such a folder
behind `PI0Policy`'s interface without the model classes (an ONNX export without torch). See docs/deploy.md.

Nothing is imported until used: `from pi0_torch.deploy import ExportedPolicy` imports numpy and onnxruntime, not torch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from pi0_torch.utils.lazy import lazy_exports

if TYPE_CHECKING:
    from pi0_torch.deploy.export import export_model
    from pi0_torch.deploy.policy import ExportedPolicy, is_export_folder

_EXPORTS = {
    "ExportedPolicy": "pi0_torch.deploy.policy",
    "export_model": "pi0_torch.deploy.export",
    "is_export_folder": "pi0_torch.deploy.policy",
}
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
__all__ = sorted(_EXPORTS)
