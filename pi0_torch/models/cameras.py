"""The camera slots of the released checkpoints, in model order (no torch, no transformers: the processors use them in
a torch-free deploy install too)."""

DEFAULT_CAMERA_NAMES = ("base_0_rgb", "left_wrist_0_rgb", "right_wrist_0_rgb")  # π0 / π0.5
FAST_CAMERA_NAMES = ("base_0_rgb", "base_1_rgb", "wrist_0_rgb")  # openpi's π0-FAST
