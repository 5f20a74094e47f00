"""`python -m pi0_torch.training ...` is `pi0-torch train ...` (for `accelerate launch -m pi0_torch.training`)."""

from pi0_torch.training.trainer import main

raise SystemExit(main())
