"""What one sampling call runs, as the engine hands it around: its checked inputs (`SamplingInputs`), the host-side
settings it was planned with (`SamplingPlan`: one CUDA graph or exported program per plan and input shapes), and the
record of what was decided for it (`SamplingDecision`, made with the plan, completed as the call runs), which
`model.last_sampling_route` reports (`SamplingRoute`)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import torch

from pi0_torch.inference.layout import PrefixLayout


@dataclass
class SamplingInputs:
    """The tensors sampling reads once its inputs are checked (what a CUDA graph holds static copies of)."""

    pixel_values: torch.Tensor  # [B, C', 3, H, W]: the cameras of the layout
    image_masks: torch.Tensor  # bool [B, C']
    input_ids: torch.Tensor  # [B, L]
    attention_mask: torch.Tensor  # [B, L]
    state: torch.Tensor | None  # [B, action_dim] (π0)
    noise: torch.Tensor  # float32 [B, horizon, action_dim]
    times: torch.Tensor  # float32 [steps]: the flow time of each Euler step
    target: torch.Tensor | None = None  # real-time chunking: float32 [B, horizon, action_dim]
    weights: torch.Tensor | None = None  # guidance: float32 [B, horizon]
    committed: torch.Tensor | None = None  # conditioning: bool [B, horizon]


@dataclass(frozen=True)
class SamplingPlan:
    """The host-side settings of one sampling call (a CUDA graph is captured per plan and input shapes)."""

    layout: PrefixLayout
    times: tuple[float, ...]
    rtc_method: str | None = None  # None: plain sampling
    max_guidance: float = 0.0
    steps: str = "torch"  # what runs the Euler steps: "torch", "triton" (the fused kernels of
    # `pi0_torch.inference.fused_pass`, five launches per decoder layer) or "persistent" (each step's decoder layers in
    # one launch, `pi0_torch.kernels.persistent`)
    attention: str = "auto"  # the attention kernel setting of its passes (`ActionSampling.attention_kernel`)

    @property
    def fused(self) -> bool:
        """The steps run the fused kernels."""
        return self.steps != "torch"

    @property
    def persistent(self) -> bool:
        return self.steps == "persistent"


@dataclass(frozen=True)
class SamplingRoute:
    """What ran a `generate_actions` call (`model.last_sampling_route`): the kernels of its Euler steps, whether it
    replayed a CUDA graph, and why it ran slower than the model's settings ask for."""

    steps: str  # "torch" (the layers' GEMMs and ATen ops), "triton" (the fused kernels, five launches per decoder layer)
    # or "persistent" (the fused kernels, each step's decoder layers in one launch)
    graph: bool  # it replayed a CUDA graph (`capture_sampling`)
    why_unfused: str | None = None  # why the steps ran "torch" (None where they ran fused)
    refusals: tuple[str, ...] = ()  # what a check refused for this call's plan and shapes, and why: its persistent
    # launch or its fused steps (first call's verification), its graph (first replay's); each made it run the next path


@dataclass
class SamplingDecision:
    """What one `generate_actions` call runs, decided once, as its plan is made (`ActionSampling.decide`), and
    completed as the call runs: each verification that refuses a fast path steps the plan down (persistent launch,
    then five launches per layer, then the torch path) and records why; the graph run records whether it replayed.
    `last_sampling_route` is its `route()`; nothing re-derives it afterwards."""

    plan: SamplingPlan
    why_unfused: str | None  # why the steps run "torch" (None where they run fused)
    refusals: list[str] = field(default_factory=list)
    replayed: bool = False

    def step_down(self, why: str) -> None:
        """The plan's fused steps were refused for this call (`why`): the next path runs (a persistent launch falls
        back to five launches per layer, those to the torch path)."""
        if self.plan.persistent:
            self.refusals.append(f"persistent launch: {why}")
            self.plan = replace(self.plan, steps="triton")
        else:
            self.refusals.append(f"fused steps: {why}")
            self.plan = replace(self.plan, steps="torch")
            self.why_unfused = f"the fused steps were refused: {why}"

    def graph_outcome(self, refusal: str | None) -> None:
        """The call ran through the captured graphs: it replayed one (`refusal` None), or sampled eagerly (why)."""
        self.replayed = refusal is None
        if refusal is not None:
            self.refusals.append(f"CUDA graph: {refusal}")

    def route(self) -> SamplingRoute:
        return SamplingRoute(self.plan.steps, self.replayed, self.why_unfused, tuple(self.refusals))
