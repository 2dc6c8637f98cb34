"""cicfw: conditional imitation (co-)learning for end-to-end steering, on Lightning + Hydra."""

__version__ = "0.2.0"

# Branch order of every mixer output: CIL command code - 2 (codes 2, 3, 4, 5).
COMMANDS = ("follow", "left", "right", "straight")
N_COMMANDS = len(COMMANDS)
# |speed| above this (km/h) is no car's: the data reader refuses a file holding one (cicfw.data.frames), the
# driving agent such an input (cicfw.export.agent), so a model only ever sees speeds it could have trained on.
MAX_ABS_SPEED_KMH = 300.0
