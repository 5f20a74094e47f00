"""Real-time chunking moved to `pi0_torch.inference.rtc` (the engine's); this path re-exports it for one release."""

from pi0_torch.inference.rtc import (  # noqa: F401
    DEFAULT_MAX_GUIDANCE, MAX_GUIDANCE, MAX_PREVIOUS_ACTION, METHODS, SCHEDULES, ChunkPrefix, check_rtc_inputs, chunk_prefix,
    guidance_weight, per_sample_steps, prefix_weights,
)
