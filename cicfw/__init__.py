"""cicfw: conditional imitation (co-)learning for end-to-end steering, on Lightning + Hydra."""

__version__ = "0.2.0"

# Branch order of every mixer output: CIL command code - 2 (codes 2, 3, 4, 5).
COMMANDS = ("follow", "left", "right", "straight")
N_COMMANDS = len(COMMANDS)
