"""Where and how the estimator runs: one :class:`DevicePolicy` per command, resolved once.

The policy turns the user's ``--device`` into a :class:`torch.device` (a one-line error when it
cannot run fR) and derives every CPU-vs-GPU decision from it: how many worker processes a folder
gets, how they split the work (whole images on a CPU; decoding + detection ahead of one searching
process on a GPU), the default batch size, and how many intra-op threads torch and OpenCV use.

Example::

    policy = DevicePolicy.resolve("cpu")
    policy.default_workers(images=500), policy.default_batch_size    # e.g. 2, 16
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import torch

from fr_torch.core.checks import resolve_device
from fr_torch.errors import FRInputError
from fr_torch.runtime.workers import usable_cores

#: Images per worker below which a worker pool does not pay for its start-up (about a second).
MIN_IMAGES_PER_WORKER = 32
#: Default cap on whole-image worker processes on a CPU (each holds its own torch, about 300 MB).
MAX_DEFAULT_WORKERS = 8
#: Default cap on detection workers feeding a GPU (each decodes + runs LSD at ~50 images/s on a
#: 640 x 480 photo, so a device searching ~1,000 images/s needs many of them).
MAX_DEFAULT_DETECTION_WORKERS = 16
#: Default images searched together per device type: a GPU needs large batches to fill it; on a
#: CPU a batch of 16 already amortises the per-call work and keeps the first results coming early.
DEFAULT_BATCH_SIZE = {"cpu": 16, "cuda": 256}


@dataclass(frozen=True)
class DevicePolicy:
    """The resolved device and the execution defaults that follow from it.

    ``device``: the :class:`torch.device` the search runs on (``cpu`` or ``cuda[:i]``).
    ``cores``: CPU cores this process may use (affinity mask capped by the cgroup quota,
    :func:`fr_torch.runtime.workers.usable_cores`).
    """

    device: torch.device
    cores: int

    @classmethod
    def resolve(cls, device: "str | torch.device | DevicePolicy" = "cpu") -> "DevicePolicy":
        """The policy of ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a torch.device or a
        policy); :class:`~fr_torch.errors.FRInputError` (one line) when it cannot run fR."""
        if isinstance(device, DevicePolicy):
            return device
        return cls(resolve_device(device), usable_cores())

    @classmethod
    def parse(cls, device: "str | torch.device" = "cpu") -> "DevicePolicy":
        """The policy of ``device`` without checking that this machine has it: for planning work
        that runs elsewhere (a Ray cluster's GPU nodes).  A malformed name is an FRInputError."""
        try:
            return cls(torch.device(device), usable_cores())
        except (RuntimeError, TypeError, ValueError):
            raise FRInputError(f"--device: unknown device {device!r} (use cpu or cuda)") from None

    @property
    def on_cpu(self) -> bool:
        return self.device.type == "cpu"

    @property
    def whole_image_workers(self) -> bool:
        """True when worker processes should calibrate whole images (CPU); False when they only
        decode and detect while this process searches on the device (GPU)."""
        return self.on_cpu

    @property
    def default_batch_size(self) -> int:
        """Images searched together by default (:data:`DEFAULT_BATCH_SIZE`)."""
        return DEFAULT_BATCH_SIZE.get(self.device.type, DEFAULT_BATCH_SIZE["cpu"])

    def default_workers(self, images: int) -> int:
        """Worker processes for ``images`` images.

        CPU: one whole-image worker per usable core, at most :data:`MAX_DEFAULT_WORKERS` and at
        most one per :data:`MIN_IMAGES_PER_WORKER` images; 0 (in-process) on one core or for
        fewer images than that.  GPU: a detection worker on every core but the one of the process
        feeding the device (at most :data:`MAX_DEFAULT_DETECTION_WORKERS`; 0 on 1-2 cores, where
        they compete with it) when there are at least two images.
        """
        if self.on_cpu:
            count = min(self.cores, MAX_DEFAULT_WORKERS, images // MIN_IMAGES_PER_WORKER)
            return count if count >= 2 else 0
        return 0 if self.cores <= 2 or images < 2 else min(self.cores - 1, MAX_DEFAULT_DETECTION_WORKERS)

    def apply_threads(self) -> None:
        """Cap torch's intra-op threads and OpenCV's threads at :attr:`cores`: in a container both
        count the host's cores, not the CPUs the quota grants, and an OpenMP region with more
        threads than CPUs stalls on every op."""

        if torch.get_num_threads() > self.cores:
            torch.set_num_threads(self.cores)
        if cv2.getNumThreads() > self.cores:
            cv2.setNumThreads(self.cores)
