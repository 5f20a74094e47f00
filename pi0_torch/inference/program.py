"""The exportable core of `generate_actions`: its sampling after the input checks, for one static plan, as a module whose
`forward` is a pure function of tensors (no host reads, no data-dependent branches), so that `torch.export` traces it.

`generate_actions` checks its inputs, reads on the host which cameras each sample shows and how many text tokens it
has, and lays the prefix out for exactly those (`InputFacts.layout`). A program fixes that layout instead: every
camera of the config and `text_length` text slots, padded (each sample's valid tokens moved to the end of the slots, as
`compact_prefix` does for any batch). Which cameras a sample shows and which tokens are valid stay inputs, as masks.
The numbers are those of `generate_actions` for the same noise: bit for bit where it lays the batch out the same way
(some sample shows every camera and fills every text slot, another does not), within float rounding otherwise (it
then attends over fewer key slots).

```python
>>> import torch
>>> from pi0_torch import PI0Config, PI0ForActionGeneration
>>> config = PI0Config.from_preset("pi0_small", num_inference_steps=2)
>>> model = PI0ForActionGeneration(config).eval()
>>> program = model.sampling_program(batch_size=1)
>>> inputs = program.example_inputs()
>>> torch.equal(program(*inputs), model.generate_actions(*inputs[:5], noise=inputs[5]))
True
>>> exported = torch.export.export(program, inputs, strict=False)  # (seconds)

```
"""

from __future__ import annotations

import torch
from torch import nn

from pi0_torch.inference.conditioning import euler_times
from pi0_torch.inference.layout import PrefixLayout
from pi0_torch.inference.plan import SamplingInputs, SamplingPlan

class SamplingProgram(nn.Module):
    """`generate_actions(pixel_values, image_masks, input_ids, attention_mask, state, noise=noise)` after its checks,
    for one batch size, step count and prompt length (see the module docstring). Make it with
    `PI0ForActionGeneration.sampling_program`; its inputs are not checked (check them first, as `generate_actions`
    does, or build them with the processor).

    Inputs: `pixel_values` `[B, C, 3, H, W]` in [-1, 1] (every camera of the config), `image_masks` bool `[B, C]`,
    `input_ids` long `[B, L]` and `attention_mask` bool `[B, L]` (L = `text_length`), `state` `[B, action_dim]` (π0;
    π0.5 ignores it), `noise` float32 `[B, horizon, action_dim]`. Output: float32 actions `[B, horizon, action_dim]` in
    normalized model space.
    """

    def __init__(self, model: nn.Module, batch_size: int, num_steps: int, text_length: int) -> None:
        super().__init__()
        self.model = model
        self.batch_size = batch_size
        self.text_length = text_length
        cameras = model.config.num_cameras  # (every camera, every text slot, padded: any sample may have fewer)
        layout = PrefixLayout(tuple(range(cameras)), cameras * model.config.tokens_per_image + text_length, padded=True)
        self.plan = SamplingPlan(layout, tuple(euler_times(num_steps)), attention="sdpa")  # (what exporters take)

    def forward(
        self,
        pixel_values: torch.Tensor,  # [B, C, 3, H, W]
        image_masks: torch.Tensor,  # bool [B, C]
        input_ids: torch.Tensor,  # long [B, L]
        attention_mask: torch.Tensor,  # bool [B, L]
        state: torch.Tensor,  # [B, action_dim]
        noise: torch.Tensor,  # float32 [B, horizon, action_dim]
    ) -> torch.Tensor:
        times = torch.tensor(self.plan.times, dtype=torch.float32, device=noise.device)
        with torch.no_grad():
            inputs = SamplingInputs(pixel_values, image_masks, input_ids, attention_mask.bool(), state, noise.float(), times)
            return self.model.sample_planned(inputs, self.plan)

    def example_inputs(self, seed: int = 0) -> tuple[torch.Tensor, ...]:
        """Inputs of the program's shapes on the model's device (random images, prompt ids and state, every camera
        shown, every text token valid; seeded): for `torch.export.export(program, program.example_inputs())`."""
        config = self.model.config
        device = next(self.model.parameters()).device
        generator = torch.Generator().manual_seed(seed)
        batch, cameras, size = self.batch_size, config.num_cameras, config.image_size
        tensors = (
            torch.rand(batch, cameras, 3, size, size, generator=generator) * 2 - 1,
            torch.ones(batch, cameras, dtype=torch.bool),
            torch.randint(0, config.vocab_size, (batch, self.text_length), generator=generator),
            torch.ones(batch, self.text_length, dtype=torch.bool),
            torch.randn(batch, config.action_dim, generator=generator),
            torch.randn(batch, config.action_horizon, config.action_dim, generator=generator),
        )
        return tuple(tensor.to(device) for tensor in tensors)
