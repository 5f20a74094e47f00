"""`make demo`: the shipped demo policy acts in closed loop on held-out tabletop episodes (the code is `pi0_torch/demo.py`).

    python examples/demo.py [--policy DIR] [--episodes 100] [--output-dir outputs/demo]
"""

import sys

from pi0_torch.demo import main

if __name__ == "__main__":
    sys.exit(main())
