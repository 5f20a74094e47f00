"""The largest value of every size and count a π0-family config holds, shared by the configs, the inference engine
and the policies (no torch, no transformers here)."""

from __future__ import annotations

# The largest value of every size and count (π0 and π0-FAST configs): far above any released model (π0: widths up to
# 16,384, 27 + 18 layers, 50 actions, 10 steps), low enough that a typo (`action_horizon: 100000000`,
# `num_hidden_layers: 1e6`, `num_inference_steps: 1e9`) is refused by name before anything is allocated or run.
SIZE_LIMITS: dict[str, int] = {
    "image_size": 2_048,
    "patch_size": 2_048,
    "vision_hidden_size": 16_384,
    "vision_intermediate_size": 65_536,
    "vision_num_layers": 256,
    "vision_num_heads": 256,
    "vlm_hidden_size": 16_384,
    "vlm_intermediate_size": 65_536,
    "expert_hidden_size": 16_384,
    "expert_intermediate_size": 65_536,
    "hidden_size": 16_384,  # π0-FAST's decoder
    "intermediate_size": 65_536,
    "num_hidden_layers": 256,
    "num_attention_heads": 256,
    "num_key_value_heads": 256,
    "head_dim": 1_024,
    "vocab_size": 1_048_576,
    "action_dim": 256,
    "action_horizon": 1_024,
    "max_token_len": 8_192,
    "num_inference_steps": 1_000,
    "max_decoding_steps": 8_192,
}

# The most samples one model call takes (a server's batch, an exported program's): far above what fits a GPU at full size.
MAX_BATCH_SIZE = 1_024
