"""`make demo`: run the committed demo policy on held-out scenes (the code is `pi0_torch/demo.py`).

    python examples/demo.py [--policy examples/demo_policy] [--plot outputs/demo_actions.png]
"""

import sys

from pi0_torch.demo import main

if __name__ == "__main__":
    sys.exit(main())
