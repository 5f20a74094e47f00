"""Fused kernels for the sampling steps of π0 / π0.5: Triton kernels (`triton_kernels`), their plain torch references
(`reference`: what each computes, the tests' oracle), and both registered as `torch.library` custom ops (`ops`).

The inference engine uses them through `pi0_torch.inference.fused_pass` and `vision_pass`; nothing here imports the
engine or the model classes.
"""

from pi0_torch.utils.triton_guard import set_aside_broken_triton

set_aside_broken_triton()  # (a triton that does not import would break torch's compiler, and every model with it)
