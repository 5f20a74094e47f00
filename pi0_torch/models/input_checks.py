"""The input checks of the π0 / π0.5 model, run before anything is computed (`forward`, `generate_actions`,
`sample_actions_reference`): every tensor's shape, dtype, device and range, read from the device in one copy, with
errors naming the argument, what was expected and what came. They read what the prefix layout needs (`InputFacts`);
nothing after them reads the device (`pi0_torch.inference.program`)."""

from __future__ import annotations

import torch

from pi0_torch.inference.layout import InputFacts
from pi0_torch.utils.validation import check_tensor as _check_tensor
from pi0_torch.utils.validation import describe, nonfinite_error

# |noise| a sampling call takes: a unit normal draw times a noise scale of at most 10 (`PolicySettings`' bound) stays
# within about ±60; 1e30 passed before and came back as actions of 1e30
MAX_NOISE = 1_000.0


class InputChecks:
    """`_check_placement` and `_check_inputs` for `PI0ForActionGeneration` (which provides `config`, `device` and
    `hf_device_map`)."""

    def _check_placement(self) -> None:
        """Refuse a model that `from_pretrained(..., device_map=...)` split across devices or offloaded ("cpu" or
        "disk" among several places): offloaded weights stay on the `meta` device until the module holding them runs,
        and this model reads some outside their module's `forward` (the flow-time terms and the action expert's norm
        scales it computes once for every sampling step)."""
        places = {_place_name(place) for place in (getattr(self, "hf_device_map", None) or {}).values()}
        if len(places) > 1 or places & {"disk", "meta"}:
            raise ValueError(
                f"{type(self).__name__} was loaded with a device_map placing its weights on {sorted(places)}; it runs with "
                "every weight on one device: load it onto one (device_map=\"cuda\", or no device_map and then "
                ".to(device); a full-size model in bf16 needs about 7 GB of GPU memory)"
            )

    def _check_inputs(
        self,
        pixel_values: torch.Tensor,
        image_masks: torch.Tensor,
        input_ids: torch.Tensor,
        attention_mask: torch.Tensor,
        state: torch.Tensor | None,
        **floats: torch.Tensor | None,
    ) -> InputFacts:
        """Validate the model inputs and read, in one device-to-host copy, every value their checks and the prefix
        layout need. Errors name the argument, expected and actual.

        `floats` are further float tensors to check when given: `noise` / `actions` `[B, horizon, action_dim]`, `time`
        `[B]` (all finite). Every tensor must be on the model's device.
        """
        config, device = self.config, self.device
        self._check_placement()
        if not isinstance(pixel_values, torch.Tensor) or pixel_values.dim() != 5:
            raise ValueError(
                f"pixel_values must be a float tensor [B, num_cameras={config.num_cameras}, 3, {config.image_size}, "
                f"{config.image_size}], got {describe(pixel_values)}"
            )
        batch = pixel_values.shape[0]
        if batch == 0:
            raise ValueError("pixel_values: a batch of 0 samples; expected at least one")
        image_shape = (batch, config.num_cameras, 3, config.image_size, config.image_size)
        _check_tensor("pixel_values", pixel_values, image_shape, floating=True, finite=False, device=device)
        _check_tensor("image_masks", image_masks, (batch, config.num_cameras), dtypes=(torch.bool,), device=device)
        if (not isinstance(input_ids, torch.Tensor) or input_ids.dim() != 2 or input_ids.shape[0] != batch
                or not 1 <= input_ids.shape[1] <= config.max_token_len):
            raise ValueError(
                f"input_ids must be a torch.Tensor [B={batch}, L] with 1 <= L <= max_token_len={config.max_token_len}, "
                f"got {describe(input_ids)}"
            )
        _check_tensor("input_ids", input_ids, tuple(input_ids.shape), dtypes=(torch.long, torch.int32), device=device)
        _check_tensor("attention_mask", attention_mask, tuple(input_ids.shape), dtypes=(torch.bool, torch.long, torch.int32), device=device)
        if not config.pi05 or state is not None:
            if state is None:
                raise ValueError(f"state is required by pi0: a float tensor [B={batch}, action_dim={config.action_dim}]")
            floats = {"state": state, **floats}
        shapes = {"state": (batch, config.action_dim), "time": (batch,)}
        checked = {name: value for name, value in floats.items() if value is not None}
        for name, value in checked.items():
            _check_tensor(name, value, shapes.get(name, (batch, config.action_horizon, config.action_dim)), floating=True, finite=False, device=device)

        # the one read: pixel range, token id range, flow-time range, finiteness, cameras shown and text tokens per sample
        time, noise = checked.get("time"), checked.get("noise")
        zeros = torch.zeros(2, device=pixel_values.device)
        ranges = torch.cat([torch.stack(pixel_values.aminmax()).float(), torch.stack(input_ids.aminmax()).float(),
                            torch.stack(time.aminmax()).float() if time is not None else zeros,
                            torch.stack(noise.aminmax()).float() if noise is not None else zeros])
        finite = [torch.isfinite(value).all() for value in checked.values()]
        read = torch.cat([
            ranges, torch.stack(finite).float() if finite else ranges.new_empty(0), image_masks.flatten().float(),
            attention_mask.sum(dim=1).float(),
        ]).cpu().tolist()
        pixel_low, pixel_high, id_low, id_high, time_low, time_high, noise_low, noise_high = read[:8]
        read = read[8:]
        if not -1.001 <= pixel_low <= pixel_high <= 1.001:  # (NaN fails every comparison)
            raise ValueError(
                f"pixel_values must lie in [-1, 1] (uint8 images map to x / 255 * 2 - 1), got range [{pixel_low:.4g}, {pixel_high:.4g}]"
            )
        if id_low < 0 or id_high >= config.vocab_size:
            raise ValueError(
                f"input_ids must be token ids in [0, vocab_size={config.vocab_size}), got values in "
                f"[{int(id_low)}, {int(id_high)}] (a tokenizer larger than the model's vocabulary?)"
            )
        for (name, value), is_finite in zip(checked.items(), read[: len(checked)]):
            if not is_finite:
                raise nonfinite_error(name, value)
        if time is not None and not 0.0 <= time_low <= time_high <= 1.0:  # (a non-finite one is named above)
            raise ValueError(f"time: flow times must lie in [0, 1] (1 is noise, 0 the actions), got values in "
                             f"[{time_low:.4g}, {time_high:.4g}]")
        if noise is not None and not -MAX_NOISE <= noise_low <= noise_high <= MAX_NOISE:
            raise ValueError(f"noise: values in [{noise_low:.4g}, {noise_high:.4g}], beyond ±{MAX_NOISE:g}: the flow starts "
                             "from a unit normal draw (times a noise scale of at most 10)")
        masks_start = len(checked)
        cameras = config.num_cameras
        shown = read[masks_start : masks_start + batch * cameras]
        facts = InputFacts(
            image_masks=tuple(tuple(bool(v) for v in shown[b * cameras : (b + 1) * cameras]) for b in range(batch)),
            text_counts=tuple(int(v) for v in read[masks_start + batch * cameras :]),
            text_length=input_ids.shape[1],
        )
        for sample, (cameras_shown, text_count) in enumerate(zip(facts.image_masks, facts.text_counts)):
            if not any(cameras_shown) or text_count == 0:
                empty = "image_masks" if not any(cameras_shown) else "attention_mask"
                raise ValueError(f"{empty}: every entry of sample {sample} is False, so the model would act on "
                                 f"{'no camera' if empty == 'image_masks' else 'no prompt token (not even BOS)'}; "
                                 "show at least one camera and one token")
        return facts


def _place_name(place: int | str | torch.device) -> str:
    """A device map's place as one name per device: "cuda:0" for 0 (on a CUDA machine), "cuda" and "cuda:0"; "disk"
    as it is."""
    try:
        device = torch.device(place)
    except RuntimeError:  # "disk"; an index where no accelerator is
        return str(place)
    return device.type if device.type in ("cpu", "meta") else f"{device.type}:{device.index or 0}"
