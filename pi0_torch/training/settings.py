"""The settings of a fine-tuning run: [`TrainSettings`] (its fields mirror `pi0-torch train`'s options), their bounds
([`check_settings`]), and openpi's optimizer recipe as their defaults (`src/openpi/training/optimizer.py`): AdamW b1
0.9, b2 0.95, eps 1e-8, weight decay 1e-10 (the Trainer leaves biases and norms undecayed, openpi decays all:
immaterial at 1e-10), global-norm clipping 1.0, and `optax.warmup_cosine_decay_schedule` from peak/(warmup+1) up to
the peak 2.5e-5 over 1,000 steps, cosine down to 2.5e-6 at `decay_steps` (openpi: 30,000 = its run length; here the
run length by default; `pi0_torch.training.pi0_trainer.openpi_learning_rate`).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from pi0_torch.utils.validation import MAX_SEED, check_float, check_int

# openpi's LoRA variants (src/openpi/models/gemma.py): gemma_2b_lora rank 16 / alpha 16, gemma_300m_lora 32 / 32
LORA_RANK_VLM = 16
LORA_RANK_EXPERT = 32

# openpi defaults (src/openpi/training/optimizer.py: AdamW, CosineDecaySchedule; config.py: TrainConfig.ema_decay)
OPENPI_PEAK_LR = 2.5e-5
OPENPI_END_LR = 2.5e-6
OPENPI_WARMUP_STEPS = 1_000
OPENPI_TRAIN_STEPS = 30_000  # the recipe's run length: its warm-up is 1/30 of it
OPENPI_BETAS = (0.9, 0.95)
OPENPI_EPS = 1e-8
OPENPI_WEIGHT_DECAY = 1e-10
OPENPI_CLIP_NORM = 1.0
OPENPI_EMA_DECAY = 0.99


@dataclass
class TrainSettings:
    """Everything a fine-tuning run needs; the fields mirror `pi0-torch train`'s options (see
    `pi0_torch.training.trainer.add_arguments`)."""

    dataset: str
    model: str
    output_dir: str
    config: str | None = None  # openpi's training config by name (`pi0_torch.training.openpi_configs`)
    config_overrides: dict[str, Any] = field(default_factory=dict)
    tokenizer: str | None = None
    norm_stats: str = "auto"  # "auto": the model folder's for the same robot space, else the dataset's
    camera_map: dict[str, str] = field(default_factory=dict)
    state_key: str = "observation.state"
    action_key: str = "action"
    train_split: str | None = None
    eval_split: str | None = None
    short_episodes: str = "pad"
    delta_action_mask: list[bool] | None = None
    value_conversion: str | None = None
    default_prompt: str | None = None  # the prompt of episodes without a task, saved with the processor
    state_in_prompt: bool | None = None  # π0.5: the discretized state in the prompt (openpi's discrete_state_input)
    max_steps: int = 30_000
    batch_size: int = 32
    gradient_accumulation_steps: int = 1
    learning_rate: float = OPENPI_PEAK_LR
    end_learning_rate: float = OPENPI_END_LR
    warmup_steps: int = OPENPI_WARMUP_STEPS
    decay_steps: int | None = None
    weight_decay: float = OPENPI_WEIGHT_DECAY
    max_grad_norm: float = OPENPI_CLIP_NORM
    ema_decay: float | None = None
    rtc_max_delay: int | None = None
    fast_tokenizer: str | None = None
    lora: bool = False
    lora_rank_vlm: int = LORA_RANK_VLM
    lora_rank_expert: int = LORA_RANK_EXPERT
    freeze: list[str] = field(default_factory=list)
    bf16: bool = False
    augment: bool = True  # openpi's image augmentation of every training sample (`pi0_torch.training.augmentation`)
    gradient_checkpointing: bool = False
    fsdp: bool = False
    seed: int = 42
    logging_steps: int = 10
    save_steps: int = 1_000
    save_total_limit: int | None = None
    eval_steps: int | None = None
    num_workers: int = 0
    threads: int | None = None  # CPU threads of torch per process; None: auto (pi0_torch.utils.threads)
    resume_from_checkpoint: str | None = None
    overwrite: bool = False  # replace an earlier run in output_dir (only a folder pi0-torch wrote)
    cpu: bool = False
    report_to: str = "none"
    progress: bool = False  # progress bars (the command line turns them on)

    @classmethod
    def from_openpi_config(cls, name: str, **values: Any) -> TrainSettings:
        """The settings of openpi's training config `name` (`pi0_torch.training.openpi_configs`: model variant and
        sizes, data features and transforms, recipe), with `values` (`dataset`, `model`, `output_dir`, and any
        setting to change) on top.

        >>> settings = TrainSettings.from_openpi_config("pi0_libero", dataset="libero", model="pi0_base",
        ...                                             output_dir="run", max_steps=100)
        >>> settings.max_steps, settings.ema_decay, settings.camera_map["left_wrist_0_rgb"], settings.config
        (100, 0.99, 'wrist_image', 'pi0_libero')
        """
        from pi0_torch.training.openpi_configs import openpi_config

        return cls(**{**openpi_config(name).settings, **values, "config": name})


# The largest value of each count of a run (a batch of 1e9 would fail on its first allocation, not by name).
RUN_LIMITS: dict[str, int] = {
    "batch_size": 65_536, "gradient_accumulation_steps": 65_536, "lora_rank_vlm": 4_096, "lora_rank_expert": 4_096,
    "num_workers": 1_024, "max_steps": 1_000_000_000, "decay_steps": 1_000_000_000, "warmup_steps": 1_000_000_000,
    "seed": MAX_SEED,
}


# How a resumed run treats a setting that differs from the one its checkpoint recorded
# (`pi0_torch.training.checkpoints.check_resume_run`); every field of `TrainSettings` is in exactly one of the three.
RESUME_REFUSED = (
    # what the run learns from: the data order and the normalization of the steps trained so far
    "dataset", "train_split", "short_episodes", "state_key", "action_key", "camera_map",
    # the model and its processor, which the checkpoint holds
    "model", "config", "config_overrides", "tokenizer", "fast_tokenizer", "norm_stats", "delta_action_mask",
    "value_conversion", "default_prompt", "state_in_prompt", "rtc_max_delay",
    # what trains: the parameters the checkpoint's optimizer state belongs to
    "lora", "lora_rank_vlm", "lora_rank_expert", "freeze", "fsdp",
    # what every step sees of its images
    "augment",
    # the batches and flow draws of every step (keyed by the seed and the position in the global batch)
    "batch_size", "seed",
)
RESUME_APPLIED = (  # from the checkpoint's step on, with a warning naming each change
    "max_steps", "learning_rate", "end_learning_rate", "warmup_steps", "decay_steps", "weight_decay", "max_grad_norm",
    "ema_decay", "gradient_accumulation_steps", "bf16", "gradient_checkpointing", "eval_split", "logging_steps",
    "save_steps", "save_total_limit", "eval_steps", "num_workers", "threads", "cpu", "report_to",
)
RESUME_UNCHECKED = ("output_dir", "resume_from_checkpoint", "overwrite", "progress")  # where and how, not what
SOURCE_SETTINGS = ("dataset", "model", "tokenizer", "fast_tokenizer", "norm_stats")  # may name files or folders


def flag_name(name: str) -> str:
    """The `pi0-torch train` option of a `TrainSettings` field.

    >>> flag_name("learning_rate"), flag_name("camera_map")
    ('--learning-rate', '--camera')
    """
    return "--camera" if name == "camera_map" else "--" + name.replace("_", "-")


def check_settings(settings: TrainSettings) -> None:
    """Refuse settings no run can use (`ValueError` naming the `pi0-torch train` flag): `--max-steps 0` would
    otherwise train one step, a zero batch or save interval would fail deep inside the Trainer."""
    for name in ("max_steps", "batch_size", "gradient_accumulation_steps", "logging_steps", "save_steps",
                 "lora_rank_vlm", "lora_rank_expert"):
        check_int(flag_name(name), getattr(settings, name), minimum=1, maximum=RUN_LIMITS.get(name))
    for name in ("decay_steps", "save_total_limit", "eval_steps"):
        if getattr(settings, name) is not None:
            check_int(flag_name(name), getattr(settings, name), minimum=1, maximum=RUN_LIMITS.get(name))
    for name in ("warmup_steps", "num_workers", "seed"):
        check_int(flag_name(name), getattr(settings, name), minimum=0, maximum=RUN_LIMITS.get(name))
    check_float("--learning-rate", settings.learning_rate, minimum=0.0, exclusive_minimum=True)
    for name in ("end_learning_rate", "weight_decay", "max_grad_norm"):
        check_float(flag_name(name), getattr(settings, name), minimum=0.0)
    if not isinstance(settings.config_overrides, Mapping):
        raise ValueError(f"--config-overrides must be a JSON object, got {type(settings.config_overrides).__name__}")
