"""The inference engine of π0 / π0.5 and π0-FAST: how `generate_actions` and `generate_tokens` run fast, beside the
model math in `pi0_torch.models` (nothing here imports it).

- `layout`: each pass's tokens laid out so that every query sees one contiguous range of keys (no mask matrix);
- `attention`: attention over those key ranges, and which kernel runs it;
- `layer_pass`: one decoder layer's sampling pass on the layer's weights (GEMMs on transposed weights, residuals
  updated in place);
- `fused_pass`: the Euler steps and the prefix pass in the fused kernels of `pi0_torch.kernels` (CUDA, bf16 / fp16);
- `checks`: what decides that a fast path may run: every gate, every tolerance, the fused ops' self-checks and each
  fused plan's verification on its first call;
- `vision_pass`: SigLIP's pass of fused sampling, on the tower's weights in fewer launches;
- `sampling`: `ActionSampling`, the mixin that gives the model `generate_actions` (the prefix cached once, the Euler
  steps, real-time chunking), `compile_sampling` and `capture_sampling`;
- `graphs`: the sampling captured as CUDA graphs by hand, each verified against eager when captured;
- `conditioning`, `plan`, `program`, `rtc`: the flow time's conditioning, a call's plan and its decision (what
  `last_sampling_route` reports), the exportable core, real-time chunking;
- π0-FAST: `token_decoding` (`TokenDecoding`, the mixin that gives the model `generate_tokens`, `compile_decoding`
  and `capture_decoding`), `fast_decoding` (decoded tokens on the fused kernels), `decoding_graphs` (hand-captured
  CUDA graphs of the prefill and the per-token step).
"""
