"""openpi's LoRA fine-tune on this package's fused projections: [`apply_lora`] adds the adapters and freezes the
Gemma, [`merge_lora`] (a live model) and [`merge_lora_state`] (a state dict) fold them into the weights.

openpi (`models/lora.py`, `models/gemma.py`, variants `gemma_2b_lora`: rank 16, `gemma_300m_lora`: rank 32, alpha =
rank so the scale is 1) adds a low-rank product to every Gemma einsum. Its factors, in this package's layout
([`LoRALinear`], `lora_a` on the input side, `lora_b` on the output side):

| projection | openpi leaves | `lora_a` | `lora_b` | update of `x` |
|---|---|---|---|---|
| `qkv_proj` | `q_einsum`, `kv_einsum` | `(N + 2K, D, r)` | `(N + 2K, r, H)` | per head: `x A[h] B[h]` |
| `o_proj` | `attn_vec_einsum` | `(N, H, r)` | `(N, r, D)` | `(x A) (B summed over heads)` |
| `gate_up_proj` | `gating_einsum_lora_*` | `(2, D, r)` | `(2, r, F)` | per half: `x A[i] B[i]` |
| `down_proj` | `linear_lora_*` | `(1, F, r)` | `(1, r, D)` | `x A B` |

So a query head has a rank-r update of its own (Gemma 2B: rank up to 8 x 16 = 128 over its queries), where one
adapter on the fused projection would share r between q, k and v. Both factors start as N(0, 0.01^2), openpi's
`LoRAConfig.init_fn`: the adapted model starts near the base model, not on it.

Everything else of the Gemma is frozen (openpi's `get_freeze_filter`: the `llm` leaves but the adapters; here also
the adapters of the projections whose output no loss reads, `trainable.loss_free_parameter_names`) and rounded to
bfloat16, as openpi's `init_train_state` casts what the filter freezes. The adapted projections' weights are stored
in bfloat16 (half their memory, the bulk of the model; each product casts them to its input's dtype); the norm
scales, the token embedding and π0.5's adaRMS modulations hold the rounded values in their own dtype, because
openpi's numbers are those of float32 arithmetic on them (the training fixture shows it for the norm scales: `1 +
scale` rounded to bfloat16 moves the first loss by 1.7e-3). The vision tower, its projection and the
action/state/time heads train in full. EMA is off (openpi's LoRA configs: an average of A and of B is not the average
of the update).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch._subclasses.fake_tensor import FakeTensor

from pi0_torch.models.configuration_pi0 import PI0Config
from pi0_torch.models.layers import ExpertLayer
from pi0_torch.training.settings import LORA_RANK_EXPERT, LORA_RANK_VLM
from pi0_torch.training.trainable import FREEZE_GROUPS, group_prefixes, loss_free_parameter_names

LORA_TARGETS = ("qkv_proj", "o_proj", "gate_up_proj", "down_proj")
HEADS_SUMMED = "o_proj"  # the projection whose update sums `lora_b` over the heads (openpi's attn_vec_einsum)
INIT_STD = 0.01  # openpi's LoRAConfig.init_fn, for both factors
GEMMA_PREFIXES = ("layers.", "embed_tokens.", "vlm_final_norm.", "expert_final_norm.", "final_norm.")  # openpi's `llm`


def lora_update(lora_a: torch.Tensor, lora_b: torch.Tensor, heads_summed: bool) -> torch.Tensor:
    """The weight update `[out, in]` (float32) of a projection's factors: `x @ update.T` is the adapters' output."""
    a, b = lora_a.float(), lora_b.float()
    if heads_summed:
        return (a.flatten(0, 1) @ b.sum(0)).T  # (N H, r) @ (r, D) -> [D, N H]
    return (a @ b).transpose(1, 2).flatten(0, 1)  # (G, in, r) @ (G, r, out) -> [G out, in]


def _quantized(tensor: torch.Tensor) -> bool:
    """Whether `tensor` holds quantized data (a torchao tensor subclass; fake tensors of memory estimates do not)."""
    return type(tensor) is not torch.Tensor and not isinstance(tensor, FakeTensor)


def _in_dtype(tensor: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """`tensor` for a product with `x` (autocast casts both itself)."""
    return tensor if tensor.dtype == x.dtype or torch.is_autocast_enabled(x.device.type) else tensor.to(x.dtype)


class LoRALinear(nn.Module):
    """A frozen bias-free projection `x W^T` plus openpi's low-rank update (the module docstring's table).

    `groups` splits the output into that many equal parts with factors each (`lora_a [G, in, r]`, `lora_b
    [G, r, out / G]`); `heads_summed` instead splits the input into `groups` heads whose `lora_b [G, r, out]` are
    summed (`lora_a [G, in / G, r]`).
    """

    def __init__(self, weight: nn.Parameter, rank: int, groups: int, heads_summed: bool = False,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        out_features, in_features = weight.shape
        self.weight = weight
        self.heads_summed = heads_summed
        a_shape = (groups, in_features // groups, rank) if heads_summed else (groups, in_features, rank)
        b_shape = (groups, rank, out_features) if heads_summed else (groups, rank, out_features // groups)
        factors = [torch.randn(shape, generator=generator) * INIT_STD for shape in (a_shape, b_shape)]
        dtype = weight.dtype if weight.dtype.is_floating_point else torch.float32
        self.lora_a, self.lora_b = (nn.Parameter(f.to(device=weight.device, dtype=dtype)) for f in factors)

    @property
    def in_features(self) -> int:
        return self.weight.shape[1]

    @property
    def out_features(self) -> int:
        return self.weight.shape[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # [..., in] -> [..., out]
        a, b = _in_dtype(self.lora_a, x), _in_dtype(self.lora_b, x)
        y = F.linear(x, _in_dtype(self.weight, x))
        if self.heads_summed:
            return y + (x @ a.flatten(0, 1)) @ b.sum(0)
        update = torch.einsum("...i,gir->...gr", x, a)
        return y + torch.einsum("...gr,gro->...go", update, b).flatten(-2)

    def merged(self, dtype: torch.dtype) -> nn.Linear:
        """A plain `nn.Linear` holding `W + update` in `dtype` (a quantized `W` dequantized: quantize the merged model
        again with `pi0-torch quantize`)."""
        weight = self.weight.dequantize() if _quantized(self.weight.data) else self.weight
        linear = nn.Linear(self.in_features, self.out_features, bias=False, device=self.weight.device, dtype=dtype)
        with torch.no_grad():
            linear.weight.copy_(weight.float() + lora_update(self.lora_a, self.lora_b, self.heads_summed))
        return linear

    def extra_repr(self) -> str:
        return f"in={self.in_features}, out={self.out_features}, lora_a={tuple(self.lora_a.shape)}, " \
               f"lora_b={tuple(self.lora_b.shape)}, heads_summed={self.heads_summed}"


def _groups(layer: ExpertLayer, target: str) -> int:
    heads, kv_heads, _ = layer.heads
    return {"qkv_proj": heads + 2 * kv_heads, "o_proj": heads, "gate_up_proj": 2, "down_proj": 1}[target]


def apply_lora(model: nn.Module, rank_vlm: int = LORA_RANK_VLM, rank_expert: int = LORA_RANK_EXPERT,
               freeze_groups: Sequence[str] = (), generator: torch.Generator | None = None) -> nn.Module:
    """openpi's LoRA on `model` (π0 / π0.5 / π0-FAST), in place: adapters of rank `rank_vlm` on every projection of
    the VLM Gemma (π0-FAST's Gemma) and of rank `rank_expert` on the action expert's, the rest of the Gemma frozen and
    stored as openpi stores it (module docstring); parameters frozen before stay frozen, and `freeze_groups`
    ("vision", "vlm": no adapters on a frozen VLM) freezes those groups too. The factors are drawn from `generator`
    (the global generator by default): every process of a run must draw the same ones.

    Returns `model`, with [`LoRALinear`] projections; [`merge_lora`] makes it plain again.

    ```python
    >>> from pi0_torch import PI0Config, PI0ForActionGeneration
    >>> from pi0_torch.training.lora import apply_lora, merge_lora
    >>> model = apply_lora(PI0ForActionGeneration(PI0Config.from_preset("pi0_small")))
    >>> model.layers[0].vlm.qkv_proj.lora_a.shape  # per head: 4 query, 1 key, 1 value head, width 64, rank 16
    torch.Size([6, 64, 16])
    >>> type(merge_lora(model).layers[0].vlm.qkv_proj).__name__
    'Linear'

    ```
    """
    for group in freeze_groups:
        if group not in FREEZE_GROUPS:
            raise ValueError(f"freeze group {group!r}: expected one of {FREEZE_GROUPS}")
    if any(isinstance(module, LoRALinear) for module in model.modules()):
        raise ValueError("the model already has LoRA adapters (apply_lora was called on it)")
    if isinstance(model.config, PI0Config):
        ranks = {"expert": rank_expert} if "vlm" in freeze_groups else {"vlm": rank_vlm, "expert": rank_expert}
    else:  # π0-FAST: one Gemma
        ranks = {"block": rank_vlm}
    for rank in ranks.values():
        if rank < 1:
            raise ValueError(f"LoRA rank {rank}: expected a positive rank")
    for layer in model.layers:
        for kind, rank in ranks.items():
            expert = getattr(layer, kind)
            for target in LORA_TARGETS:
                linear = getattr(expert, target)
                if type(linear) is not nn.Linear or linear.bias is not None:
                    raise ValueError(f"{kind}.{target} is a {type(linear).__name__}, not a bias-free nn.Linear: "
                                     "LoRA adapts the plain Gemma projections")
                setattr(expert, target, LoRALinear(linear.weight, rank, _groups(expert, target), target == HEADS_SUMMED,
                                                   generator))
    frozen = GEMMA_PREFIXES + tuple(prefix for group in freeze_groups for prefix in group_prefixes(model, group))
    loss_free = set(loss_free_parameter_names(model))  # (their adapters too: no gradient ever reaches them)
    for name, param in model.named_parameters():
        if name in loss_free or (name.startswith(frozen) and not name.rsplit(".", 1)[-1].startswith("lora_")):
            param.requires_grad_(False)
    _store_frozen_gemma_as_openpi(model)
    return model


def _store_frozen_gemma_as_openpi(model: nn.Module) -> None:
    """The frozen Gemma parameters rounded to bfloat16 (openpi's `init_train_state`): the adapted projections' weights
    stored so (each product casts them to its input's dtype), the others (norm scales, token embedding, adaRMS
    modulations) rounded in place in their own dtype, where they compute as openpi's do. Adapters (the loss-free ones
    are frozen too) and quantized (tensor-subclass) weights are left as they are."""
    for name, module in model.named_modules():
        if not f"{name}.".startswith(GEMMA_PREFIXES):
            continue
        for param_name, param in module.named_parameters(recurse=False):
            kept = param_name.startswith("lora_") or _quantized(param.data) or not param.is_floating_point()
            if param.requires_grad or kept:
                continue
            rounded = param.detach().to(torch.bfloat16)
            stored = rounded if isinstance(module, LoRALinear) else rounded.to(param.dtype)
            setattr(module, param_name, nn.Parameter(stored, requires_grad=False))


def merge_lora(model: nn.Module) -> nn.Module:
    """`model` with each [`LoRALinear`] replaced by a plain `nn.Linear` holding `W + update`, and every parameter in
    the adapters' dtype again (the frozen bfloat16 ones included); a model without adapters is returned as is."""
    adapted = [(name, module) for name, module in model.named_modules() if isinstance(module, LoRALinear)]
    if not adapted:
        return model
    dtype = adapted[0][1].lora_a.dtype
    for name, module in adapted:
        parent, attribute = name.rsplit(".", 1)
        setattr(model.get_submodule(parent), attribute, module.merged(dtype))
    return model.to(dtype)


def merge_lora_state(state: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A state dict of a LoRA model (the weights and `lora_a` / `lora_b` of each [`LoRALinear`]) -> the plain model's,
    every floating-point tensor in the adapters' dtype; a state without adapters is returned as a copy of itself."""
    prefixes = [name.removesuffix(".lora_a") for name in state if name.endswith(".lora_a")]
    if not prefixes:
        return dict(state)
    dtype = state[f"{prefixes[0]}.lora_a"].dtype
    merged = {name: tensor for name, tensor in state.items() if name.rsplit(".", 1)[-1] not in ("lora_a", "lora_b")}
    for prefix in prefixes:
        update = lora_update(state[f"{prefix}.lora_a"], state[f"{prefix}.lora_b"], prefix.endswith(HEADS_SUMMED))
        merged[f"{prefix}.weight"] = state[f"{prefix}.weight"].float() + update
    return {name: tensor.to(dtype) if tensor.is_floating_point() else tensor for name, tensor in merged.items()}
