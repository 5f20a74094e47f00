"""This package's training, step by step, against openpi's own JAX training of the same model on the same batches
(`tests/fixtures/openpi_training`, recorded by `tests/fixtures/make_openpi_training_fixture.py` from openpi 15a9616a):
20 optimizer steps of the small π0 fixture model with openpi's optimizer, schedule, clipping and EMA, through the
trainer `pi0-torch train` builds (`build_trainer`), fed openpi's recorded noise and flow times through the batch.

Matched: the loss of every step (float32 1e-5 relative; openpi's bf16 numerics 1e-2), the gradient norm before
clipping (1e-4), and at the end every parameter and its EMA (1e-4 relative, per tensor): measured 1.6e-7 for the
losses, 2e-6 for the parameters. Two differences were found reading openpi and fixed in `PI0Trainer` (the gradient
clipping had torch's epsilon, `norm + 1e-6`; weight decay skipped biases and norms, where openpi decays every
parameter); at openpi's weight decay of 1e-10 and gradient norms near 1 neither moves these numbers beyond 1e-7.
openpi's LoRA training (its `gemma_2b_lora` and `gemma_300m_lora` variants and freeze filter, frozen weights in
bfloat16) is matched the same way over the trainable parameters, the frozen ones bit for bit; and an openpi LoRA tree
converts with its adapters merged, giving openpi's LoRA loss."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from transformers import TrainerCallback

from pi0_torch import PI0ForActionGeneration
from pi0_torch.conversion.openpi_weights import load_openpi_params
from pi0_torch.training.lora import GEMMA_PREFIXES, apply_lora
from pi0_torch.training.settings import TrainSettings
from pi0_torch.training.trainer import build_trainer

from conftest import OpenpiReference

FIXTURES = Path(__file__).parent / "fixtures" / "openpi_training"
# parameters whose true gradient is zero: Adam turns rounding noise into updates there (openpi's own two runs differ)
NOISY = ("vision_tower.encoder.layers.0.self_attn.k_proj.bias", "vision_tower.encoder.layers.1.self_attn.k_proj.bias")


class Recorder(TrainerCallback):
    """The raw weights at the end of training, before the EMA callback copies the averages in."""

    def __init__(self) -> None:
        self.weights: dict[str, torch.Tensor] = {}

    def on_train_end(self, args: Any, state: Any, control: Any, model: torch.nn.Module | None = None, **kwargs: Any) -> None:
        self.weights = {name: value.detach().clone() for name, value in model.state_dict().items()}


def openpi_lora_factors(recorded: dict[str, Any], stage: str, config: Any) -> dict[str, torch.Tensor]:
    """The adapters of the fixture's openpi LoRA tree (`stage` "init" or "params") as this package's [`LoRALinear`]
    factors: q and the kv pair stacked per head, the MLP's down projection as one group."""
    factors = {}
    llm = "PaliGemma/llm/layers"
    for kind, s in (("vlm", ""), ("expert", "_1")):
        def leaf(path: str) -> np.ndarray:
            return recorded[f"{stage}/{llm}/{path}"]
        for layer in range(config.num_hidden_layers):
            prefix = f"layers.{layer}.{kind}"
            for factor in ("a", "b"):
                q, kv = leaf(f"attn/q_einsum{s}/lora_{factor}")[layer], leaf(f"attn/kv_einsum{s}/lora_{factor}")[layer]
                parts = {
                    "qkv_proj": np.concatenate([q, kv[0], kv[1]]),  # (N + 2K, D, r) / (N + 2K, r, H)
                    "o_proj": leaf(f"attn/attn_vec_einsum{s}/lora_{factor}")[layer],
                    "gate_up_proj": leaf(f"mlp{s}/gating_einsum_lora_{factor}")[layer],
                    "down_proj": leaf(f"mlp{s}/linear_lora_{factor}")[layer][None],
                }
                for target, value in parts.items():
                    factors[f"{prefix}.{target}.lora_{factor}"] = torch.from_numpy(np.ascontiguousarray(value))
    return factors


def train_like_openpi(case: str, tmp_path: Path) -> tuple[dict[str, Any], list[float], list[float], dict[str, Any]]:
    """Train the fixture model on openpi's recorded batch and draws for `case` ("fp32", "bf16", "lora"): openpi's
    record, the losses and gradient norms of every step, and {"params": (ours, openpi's) at the end, "ema": the same
    for the averages, or for LoRA "start": the adapted model before training}."""
    recorded = dict(np.load(FIXTURES / f"{case}.npz"))
    reference = OpenpiReference("pi0_small")
    model = reference.model()
    lora = case == "lora"
    if lora:  # openpi's variants' ranks, its recorded initial adapters
        apply_lora(model, int(recorded["lora/paligemma/attn/rank"]), int(recorded["lora/action_expert/attn/rank"]))
        assert not model.load_state_dict(openpi_lora_factors(recorded, "init", model.config), strict=False).unexpected_keys
        start = {name: value.clone() for name, value in model.state_dict().items()}
    batch = {**reference.model_inputs(), "actions": reference.tensor("inputs/actions")}
    steps = int(recorded["num_steps"])
    settings = TrainSettings(
        dataset="openpi fixture", model="pi0_small", output_dir=str(tmp_path), max_steps=steps,
        batch_size=int(recorded["batch_size"]), learning_rate=float(recorded["lr_peak"]),
        end_learning_rate=float(recorded["lr_end"]), warmup_steps=int(recorded["lr_warmup_steps"]),
        decay_steps=int(recorded["lr_decay_steps"]), weight_decay=float(recorded["weight_decay"]),
        max_grad_norm=float(recorded["clip_gradient_norm"]),
        ema_decay=float(recorded["ema_decay"]) if recorded["has_ema"] else None, lora=lora, bf16=case == "bf16",
        augment=False, seed=int(recorded["seed"]), logging_steps=1, save_steps=10 * steps, cpu=True,
    )
    calls = iter(range(steps))

    def collate(samples: list[Any]) -> dict[str, torch.Tensor]:  # the same batch, with the step's recorded draws
        step = next(calls)
        return {**batch, "noise": torch.from_numpy(recorded["noise"][step]), "time": torch.from_numpy(recorded["time"][step])}

    recorder = Recorder()
    trainer, _ = build_trainer(settings, model.config, model, {}, list(range(steps * settings.batch_size)), None, collate,
                               recorder)
    losses, norms = [], []
    compute_loss, clip = trainer.compute_loss, trainer._clip_grad_norm
    trainer.compute_loss = lambda *args, **kwargs: losses.append(compute_loss(*args, **kwargs)) or losses[-1]
    trainer._clip_grad_norm = lambda *args: norms.append(clip(*args)) or norms[-1]
    trainer.train()
    losses, norms = [float(loss.detach()) for loss in losses], [float(norm) for norm in norms]
    expected = PI0ForActionGeneration(reference.config)
    final = {key[len("params/"):]: value for key, value in recorded.items() if key.startswith("params/")}
    if lora:  # openpi's weights without its adapters merged, and its adapters
        load_openpi_params(expected, {path: value for path, value in final.items() if "lora" not in path})
        theirs = expected.state_dict() | openpi_lora_factors(recorded, "params", model.config)
        return recorded, losses, norms, {"params": (recorder.weights, theirs), "start": start}
    load_openpi_params(expected, final)
    averaged = PI0ForActionGeneration(reference.config)
    load_openpi_params(averaged, {key[len("ema/"):]: value for key, value in recorded.items() if key.startswith("ema/")})
    ema = {name: value.detach() for name, value in trainer.model.state_dict().items()}  # (the averages, copied in)
    return recorded, losses, norms, {"params": (recorder.weights, expected.state_dict()), "ema": (ema, averaged.state_dict())}


def worst(ours: dict[str, torch.Tensor], theirs: dict[str, torch.Tensor]) -> tuple[float, str]:
    """The largest per-tensor error over the parameters: `||ours - theirs|| / ||theirs||`, or for `NOISY` the largest
    absolute difference. (Element-wise, one embedding row whose gradient is near zero is 1.2e-4 of the table's
    largest value off: Adam scales rounding noise up there as on the key biases.)"""
    errors = {}
    for name, want in theirs.items():
        difference = ours[name].float() - want.float()
        errors[name] = (float(difference.abs().max()) if name in NOISY
                        else float(difference.norm() / max(float(want.float().norm()), 1e-12)))
    name = max(errors, key=errors.get)
    return errors[name], name


def test_float32_training_equals_openpis_step_for_step(tmp_path: Path) -> None:
    recorded, losses, norms, weights = train_like_openpi("fp32", tmp_path)
    assert len(losses) == len(recorded["loss"]) == 20
    assert np.abs(np.array(losses) - recorded["loss"]).max() / np.abs(recorded["loss"]).max() <= 1e-5
    assert np.abs(np.array(norms) - recorded["grad_norm"]).max() / recorded["grad_norm"].max() <= 1e-4
    for kind in ("params", "ema"):
        error, name = worst(*weights[kind])
        assert error <= 1e-4, (kind, name, error)


def test_bf16_training_follows_openpis_within_bf16(tmp_path: Path) -> None:
    """openpi's bf16 numerics (float32 weights, bf16 activations) against this package's bf16 autocast: each step's
    loss within 1e-2 (XLA fuses and rounds differently: two of openpi's own builds differ by 2e-4)."""
    recorded, losses, _, _ = train_like_openpi("bf16", tmp_path)
    assert np.abs(np.array(losses) - recorded["loss"]).max() / np.abs(recorded["loss"]).max() <= 1e-2


def test_lora_training_equals_openpis_step_for_step(tmp_path: Path) -> None:
    """openpi's LoRA fine-tune (`gemma_2b_lora` rank 16 on the VLM, `gemma_300m_lora` rank 32 on the action expert,
    its freeze filter, the frozen weights in bfloat16, no EMA) from openpi's recorded initial adapters: each step's loss
    and gradient norm, and at the end the adapters and the other trained parameters, as in float32; the frozen Gemma
    weights bit for bit openpi's (bfloat16-rounded once, then untouched)."""
    recorded, losses, norms, weights = train_like_openpi("lora", tmp_path)
    assert len(losses) == len(recorded["loss"]) == 20
    assert np.abs(np.array(losses) - recorded["loss"]).max() / np.abs(recorded["loss"]).max() <= 1e-5
    assert np.abs(np.array(norms) - recorded["grad_norm"]).max() / recorded["grad_norm"].max() <= 1e-4
    (ours, theirs), start = weights["params"], weights["start"]
    frozen = {name for name in ours if name.startswith(GEMMA_PREFIXES) and ".lora_" not in name}
    assert frozen and sum(".lora_" in name for name in ours) == 2 * 4 * 2 * 3  # (a, b) x 4 projections x 2 experts x 3 layers
    for name in frozen:
        assert ours[name].dtype == (torch.bfloat16 if name.endswith("_proj.weight") else torch.float32), name
        assert torch.equal(ours[name], start[name]) and torch.equal(ours[name].float(), theirs[name]), name
    error, name = worst({name: ours[name] for name in ours if name not in frozen},
                        {name: theirs[name] for name in ours if name not in frozen})
    assert error <= 1e-4, (name, error)


def openpi_lora_tree(recorded: dict[str, Any], stage: str) -> dict[str, np.ndarray]:
    """openpi's LoRA tree (adapters on both experts) at the start (`stage` "init") or after its 20 steps ("params"):
    the frozen Gemma weights as openpi keeps them (bf16-rounded, unchanged by training)."""
    start = OpenpiReference("pi0_small").params
    tree = {}
    for path, frozen in zip(map(str, recorded["param_paths"]), recorded["frozen_cast_to_bf16"]):
        if stage == "params" or frozen:
            tree[path] = recorded[f"params/{path}"]
        else:
            tree[path] = recorded[f"init/{path}"] if "lora" in path else start[path]
    return tree


def test_an_openpi_lora_fine_tune_converts_with_its_adapters_merged(tmp_path: Path) -> None:
    """openpi's LoRA (per head on q, k and v, the attention output's B summed over heads, the MLP's unscaled): its
    tree loads with the adapters merged into the weights, and the merged model's loss of every example and action
    step equals openpi's own LoRA forward (step 0 of the fixture, adapters N(0, 0.1^2) so they matter). The orbax
    conversion gives the same weights, and reads every adapter."""
    from pi0_torch.conversion.convert_openpi import convert_openpi_checkpoint
    from pi0_torch.conversion.orbax_reader import write_orbax_checkpoint

    recorded = dict(np.load(FIXTURES / "lora.npz"))
    reference = OpenpiReference("pi0_small")
    merged = PI0ForActionGeneration(reference.config).eval()
    load_openpi_params(merged, openpi_lora_tree(recorded, "init"))
    actions, noise = reference.tensor("inputs/actions"), torch.from_numpy(recorded["noise"][0])
    with torch.no_grad():
        velocity = merged(**reference.model_inputs(), actions=actions, noise=noise,
                          time=torch.from_numpy(recorded["time"][0])).velocity
    per_example = ((velocity - (noise - actions)) ** 2).mean(-1).numpy()  # [B, horizon], openpi's compute_loss
    want = recorded["loss_per_example"][0]
    assert np.abs(per_example - want).max() / np.abs(want).max() <= 1e-5
    without = reference.model()  # (the adapters change the loss: the check above can fail)
    with torch.no_grad():
        assert not torch.allclose(without(**reference.model_inputs(), actions=actions, noise=noise,
                                          time=torch.from_numpy(recorded["time"][0])).velocity, velocity, atol=1e-3)

    final = openpi_lora_tree(recorded, "params")
    write_orbax_checkpoint(tmp_path / "ckpt" / "params", final)
    out = convert_openpi_checkpoint(tmp_path / "ckpt", tmp_path / "out", progress=False).output_dir  # (every leaf used)
    expected = PI0ForActionGeneration(reference.config)
    load_openpi_params(expected, final)
    converted = PI0ForActionGeneration.from_pretrained(out).state_dict()
    assert all(torch.equal(tensor, converted[name]) for name, tensor in expected.state_dict().items())
    broken = {path: array for path, array in final.items() if not path.endswith("linear_lora_b")}
    with pytest.raises(ValueError, match=r"missing: .*mlp/linear_lora_b, .*mlp_1/linear_lora_b"):
        load_openpi_params(PI0ForActionGeneration(reference.config), broken)
