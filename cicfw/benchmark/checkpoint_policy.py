"""The suite's policy that drives with a trained model: a checkpoint, or a model ``cicfw export`` wrote.

Loading and checking the checkpoint is the model layer's (``cicfw.model.checkpoint``); running it is the
agent's (``cicfw.export.agent``), so the suite, a CARLA client and a user's own stack share one inference path.
"""
from __future__ import annotations

import numpy as np

from cicfw.benchmark.policy import Observations, Policy
from cicfw.core.errors import CicfwError, ConfigError
from cicfw.export.agent import LOADABLE, Agent
from cicfw.model.checkpoint import CheckpointBytes
from cicfw.sim.render.camera import CAMERAS


class CheckpointPolicy(Policy):
    """A trained CICModule steering from ``camera`` (the centre one as in the paper; another is named in
    the row label), in eval mode, no grad.

    It drives through ``cicfw.export.agent.Agent`` (one inference path for the suite, CARLA and a user's own
    stack): the CIL command code selects the branch (index = code - 2). ``fuse`` prepares the network for
    inference (``prepare_for_inference``: BatchNorm folded into the convolutions, NHWC layout);
    ``device`` is where it runs (``auto``: a CUDA GPU when there is one, else the CPU). ``checkpoint``
    may also be a model written by ``cicfw export`` (``.onnx``, TorchScript ``.pt``). The file is read once:
    ``source`` holds the bytes the policy was built from (the evaluation hashes them, and hands them to its
    worker processes, which pass them back as ``checkpoint``: annotated ``str`` alone, since the config's
    schema comes from this signature and a config gives a path).
    """

    def __init__(self, checkpoint: str | None = None, camera: str = "centre", threads: int | None = None,
                 label: str | None = None, fuse: bool = True, device: str = "auto") -> None:
        if not checkpoint:
            raise CicfwError("policy=checkpoint needs checkpoint=path/to.ckpt (or use policy=expert)")
        if camera not in CAMERAS:  # else the first step fails, after the run folder holds a partial run
            raise ConfigError("policy.camera", camera, "one of " + ", ".join(CAMERAS))
        try:
            source = checkpoint if isinstance(checkpoint, CheckpointBytes) else CheckpointBytes.read(checkpoint,
                                                                                                    LOADABLE)
            self.agent = Agent.load(source, threads=threads, device=device, fuse=fuse)
        except ValueError as err:
            if str(err).startswith("device="):
                raise CicfwError(f"policy.{err}") from None
            raise
        self.path = str(checkpoint)
        self.source: CheckpointBytes | None = source  # None in a worker process once built (runner._worker)
        self.device = self.agent.device
        self.model = self.agent.model  # the CICModule (None for an exported model)
        self.cameras = (camera,)
        self.label = label or self.agent.label + ("" if camera == "centre" else f" ({camera} camera)")

    def act(self, obs: Observations) -> np.ndarray:
        return self.agent.act(obs.images[self.cameras[0]], obs.speed_kmh, obs.command)
