"""Quickstart: build a π0 model, train one step, sample an action chunk, save and reload it.

Runs on CPU in seconds with the small preset; use `PI0Config.pi0()` / `.pi05()` (or a converted openpi checkpoint
folder with `from_pretrained`) for the released sizes.

    python examples/quickstart.py
"""

import tempfile

import torch

from pi0_torch import PI0Config, PI0ForActionGeneration

torch.manual_seed(0)
config = PI0Config.from_preset("pi05_small")  # π0.5; "pi0_small" for π0
model = PI0ForActionGeneration(config)

batch_size = 2
inputs = dict(
    pixel_values=torch.rand(batch_size, config.num_cameras, 3, 224, 224) * 2 - 1,  # [-1, 1], channels first
    image_masks=torch.tensor([[True, True, True], [True, True, False]]),  # second sample: no right wrist camera
    input_ids=torch.randint(1, config.vocab_size, (batch_size, config.max_token_len)),
    attention_mask=torch.arange(config.max_token_len)[None, :] < torch.tensor([[12], [20]]),
    state=torch.randn(batch_size, config.action_dim),  # π0 reads it; π0.5 takes state through the prompt
)

# one training step: the flow-matching loss is a scalar, ready for the HF Trainer
actions = torch.randn(batch_size, config.action_horizon, config.action_dim)
optimizer = torch.optim.AdamW(model.parameters(), lr=1e-4, betas=(0.9, 0.95))
loss = model(**inputs, actions=actions).loss
loss.backward()
optimizer.step()
print(f"loss {loss.item():.4f}")

# sampling: the prefix is encoded once, then 10 Euler steps run the action expert against its cached k/v
model.eval()
chunk = model.generate_actions(**inputs, generator=torch.Generator().manual_seed(0))
print("action chunk", tuple(chunk.shape))  # (2, 50, 32), normalized model space

with tempfile.TemporaryDirectory() as folder:
    model.save_pretrained(folder)
    reloaded = PI0ForActionGeneration.from_pretrained(folder)
    again = reloaded.generate_actions(**inputs, generator=torch.Generator().manual_seed(0))
    print("reloaded model gives the same chunk:", torch.equal(chunk, again))
