"""openpi's training configs by name: `pi0-torch train --config pi0_libero` takes the values openpi's `TrainConfig` of
that name trains with (`src/openpi/training/config.py`, commit 15a9616a), each overridable by its own flag.

What a name sets, as openpi's config does:

- the model variant (π0 or π0.5, checked against `--model`: the converted base checkpoint openpi's weight loader
  names), the action horizon and the prompt length (`config_overrides`);
- the data: the dataset's camera, state and action features (openpi's repack transform), `DeltaActions` masks, the
  ALOHA value conversion (`adapt_to_pi`), the default prompt, and which norm stats (the dataset's, or the base
  model's where openpi reads them from its assets);
- the recipe: batch size, steps, the warm-up cosine schedule, gradient clipping, EMA, LoRA.

Configs this package cannot follow are refused by name, saying why (`REFUSED`).

```python
>>> recipe = openpi_config("pi05_libero")
>>> recipe.variant, recipe.settings["batch_size"], recipe.settings["ema_decay"], recipe.settings["config_overrides"]
('pi05', 256, 0.999, {'action_horizon': 10})

```
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

# openpi's defaults: TrainConfig (batch 32, 30k steps, EMA 0.99), CosineDecaySchedule (warm-up 1k, peak 2.5e-5, decay
# over 30k steps to 2.5e-6), AdamW (clipping at 1.0); `pi0-torch train`'s own defaults are the same but for EMA
_DEFAULTS: dict[str, Any] = dict(batch_size=32, max_steps=30_000, learning_rate=2.5e-5, end_learning_rate=2.5e-6,
                                 warmup_steps=1_000, decay_steps=30_000, max_grad_norm=1.0, ema_decay=0.99, lora=False)
# LeRobotLiberoDataConfig: the repack transform's keys, and LiberoInputs' cameras (the right wrist absent: masked)
_LIBERO = dict(camera_map={"base_0_rgb": "image", "left_wrist_0_rgb": "wrist_image"}, state_key="state",
               action_key="actions", norm_stats="dataset")
_LIBERO_DELTAS = [True] * 6 + [False]  # extra_delta_transform: make_bool_mask(6, -1)
# LeRobotAlohaDataConfig: AlohaInputs(adapt_to_pi=True) and DeltaActions(make_bool_mask(6, -1, 6, -1))
_ALOHA_DELTAS = [True] * 6 + [False] + [True] * 6 + [False]
_ALOHA_CAMERAS = {"base_0_rgb": "observation.images.cam_high", "left_wrist_0_rgb": "observation.images.cam_left_wrist",
                  "right_wrist_0_rgb": "observation.images.cam_right_wrist"}


@dataclass(frozen=True)
class OpenpiRecipe:
    """One openpi config: the model variant it fine-tunes (`pi0`, `pi05`) and the `TrainSettings` values it sets."""

    name: str
    variant: str
    base: str  # the checkpoint openpi's weight loader starts from
    settings: dict[str, Any]


def _recipe(name: str, variant: str, base: str, **settings: Any) -> OpenpiRecipe:
    return OpenpiRecipe(name, variant, base, {**_DEFAULTS, **settings})


OPENPI_CONFIGS: dict[str, OpenpiRecipe] = {recipe.name: recipe for recipe in (
    _recipe("pi0_libero", "pi0", "pi0_base", **_LIBERO, delta_action_mask=_LIBERO_DELTAS),
    _recipe("pi0_libero_low_mem_finetune", "pi0", "pi0_base", **_LIBERO, delta_action_mask=_LIBERO_DELTAS, lora=True,
            ema_decay=None),
    _recipe("pi05_libero", "pi05", "pi05_base", **_LIBERO, config_overrides={"action_horizon": 10},
            state_in_prompt=False, batch_size=256,
            learning_rate=5e-5, end_learning_rate=5e-5, warmup_steps=10_000, decay_steps=1_000_000, ema_decay=0.999),
    _recipe("pi0_aloha_sim", "pi0", "pi0_base", camera_map={"base_0_rgb": "observation.images.top"},
            state_key="observation.state", action_key="action", value_conversion="aloha", norm_stats="dataset",
            default_prompt="Transfer cube", max_steps=20_000),
    _recipe("pi0_aloha_pen_uncap", "pi0", "pi0_base", camera_map=_ALOHA_CAMERAS, state_key="observation.state",
            action_key="action", value_conversion="aloha", delta_action_mask=_ALOHA_DELTAS, norm_stats="model",
            default_prompt="uncap the pen", max_steps=20_000),
    _recipe("pi05_aloha_pen_uncap", "pi05", "pi05_base", camera_map=_ALOHA_CAMERAS, state_key="observation.state",
            action_key="action", value_conversion="aloha", delta_action_mask=_ALOHA_DELTAS, norm_stats="model",
            default_prompt="uncap the pen", max_steps=20_000, batch_size=64),
)}

REFUSED: dict[str, str] = {
    **{name: "an inference config in openpi (no dataset to train on): serve the converted checkpoint instead"
       for name in ("pi0_aloha", "pi05_aloha", "pi0_aloha_towel", "pi0_aloha_tupperware", "pi0_droid",
                    "pi0_fast_droid", "pi05_droid")},
    **{name: "it trains on DROID's RLDS release, and pi0-torch reads LeRobot datasets: convert the episodes to LeRobot "
             "(openpi's examples/droid/convert_droid_data_to_lerobot.py)"
       for name in ("pi0_fast_full_droid_finetune", "pi05_full_droid_finetune")},
    "pi05_droid_finetune": "its state is two dataset features (joint_position, gripper_position) and pi0-torch reads "
                           "one: write them as one vector feature and pass --state-key with the base model's settings",
    **{name: "openpi's π0-FAST LIBERO config feeds the absent right-wrist camera as a shown all-black image, and "
             "pi0-torch's data loader masks absent cameras: train π0-FAST with its own flags"
       for name in ("pi0_fast_libero", "pi0_fast_libero_low_mem_finetune")},
    **{name: "a debugging config of openpi (fake data)" for name in ("debug", "debug_restore", "debug_pi05")},
}


def openpi_config(name: str) -> OpenpiRecipe:
    """The recipe of openpi's config `name`; a `ValueError` naming why for a config this package cannot follow, or
    listing the names for an unknown one."""
    if name in REFUSED:
        raise ValueError(f"--config {name}: {REFUSED[name]}")
    if name not in OPENPI_CONFIGS:
        raise ValueError(f"--config {name!r} is not one of openpi's training configs that pi0-torch follows: "
                         f"{', '.join(OPENPI_CONFIGS)}")
    return OPENPI_CONFIGS[name]
