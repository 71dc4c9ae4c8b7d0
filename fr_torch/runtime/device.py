"""Where and how the estimator runs: one :class:`DevicePolicy` per command, resolved once.

The policy turns the user's ``--device`` into a :class:`torch.device` (a one-line error when it
cannot run fR) and derives every CPU-vs-GPU decision from it: how many worker processes a folder
gets, how they split the work (whole images on a CPU; decoding + detection ahead of one searching
process on a GPU), the default batch size, and how many intra-op threads torch and OpenCV use.

Threads on a CPU (:attr:`DevicePolicy.threads`, from ``FR_THREADS`` unless given; docs/cpu-threads.md):

* ``"auto"`` (default): every search call (:meth:`DevicePolicy.search_threads`) runs with one
  intra-op thread per core that other processes leave free (:mod:`fr_torch.runtime.cpuload`), at
  least one and at most torch's thread count in effect (a command sets it to the usable cores,
  :meth:`DevicePolicy.apply_threads`; worker processes to one); torch's setting is restored on return.
  An OpenMP parallel region waits for its slowest thread, so a thread whose core another process
  holds stalls every op (4-5x slower on 2 cores with one busy neighbour); one thread fewer does not.
* ``N`` (a positive integer): every search call runs with at most N threads, whatever the load.
* ``"torch"``: fR never changes torch's thread count (beyond :meth:`DevicePolicy.apply_threads`'s
  cap at the usable cores).

Example::

    policy = DevicePolicy.resolve("cpu")
    policy.default_workers(images=500), policy.default_batch_size    # e.g. 2, 16
    DevicePolicy.resolve("cpu", threads=1)                            # one thread, whatever the load
"""
from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass
from typing import Iterator, Union

import cv2
import torch

from fr_torch.core.settings.checks import resolve_device
from fr_torch.errors import FRInputError
from fr_torch.runtime import cpuload
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
#: :attr:`DevicePolicy.decode` settings.
DECODE_CHOICES = ("auto", "device", "host")
#: The line detector of an estimator whose caller names none, per device type: on a GPU,
#: torch-lines runs on the device beside the search (no host detection workers needed).
DEFAULT_DETECTOR = {"cpu": "lsd", "cuda": "torch-lines"}
#: Environment variable holding the default :attr:`DevicePolicy.threads` (``auto``, ``torch`` or N).
THREADS_ENV = "FR_THREADS"
AUTO_THREADS = "auto"
TORCH_THREADS = "torch"
#: :attr:`DevicePolicy.threads`: ``"auto"``, ``"torch"`` or a fixed positive count.
ThreadSetting = Union[str, int]


def parse_threads(value: "str | int | None", source: str = THREADS_ENV) -> ThreadSetting:
    """The thread setting of ``value`` (``auto``, ``torch``, a positive integer; None or empty =
    ``auto``); FRInputError (one line, naming ``source``) otherwise."""
    if value is None or (isinstance(value, str) and not value.strip()):
        return AUTO_THREADS
    if isinstance(value, str):
        text = value.strip().lower()
        if text in (AUTO_THREADS, TORCH_THREADS):
            return text
        value = text
    try:
        count = int(value)
        if isinstance(value, float) or count < 1:
            raise ValueError
    except (TypeError, ValueError):
        raise FRInputError(f"{source}: expected auto, torch or a positive number of threads, got {value!r}") from None
    return count


#: Share of a core other processes must leave free for it to get a search thread.  On 2 cores a
#: second thread still paid beside a neighbour busy 25 % of the time and lost 1.6-1.7x at 50 %
#: (results/decisions/40.md): an OpenMP region waits for its slowest thread, so a part-time
#: neighbour costs more than the thread brings.
FREE_CORE_SHARE = 0.65


def threads_for_free_cores(free_cores: "float | None", ceiling: int) -> int:
    """Intra-op threads for a search: the cores other processes leave free, a partly free core
    counting when at least :data:`FREE_CORE_SHARE` of it is; at least 1 and at most ``ceiling``;
    ``ceiling`` when the free cores are unknown (None)."""
    ceiling = max(1, ceiling)
    if free_cores is None:
        return ceiling
    return max(1, min(ceiling, math.floor(free_cores + 1.0 - FREE_CORE_SHARE)))


@dataclass(frozen=True)
class DevicePolicy:
    """The resolved device and the execution defaults that follow from it.

    ``device``: the :class:`torch.device` the search runs on (``cpu`` or ``cuda[:i]``).
    ``cores``: CPU cores this process may use (affinity mask capped by the cgroup quota,
    :func:`fr_torch.runtime.workers.usable_cores`).
    ``threads``: intra-op threads of a search on a CPU: ``"auto"`` (adapt to the load),
    ``"torch"`` (leave torch's count) or a fixed positive count (module docstring).
    ``decode``: where image files are decoded and detected on a GPU: ``"auto"`` (on the device
    when the detector detects batches and torchvision's ``decode_jpeg`` loads,
    :mod:`fr_torch.runtime.device_pipeline`), ``"device"`` (that, or a one-line error) or
    ``"host"`` (host worker processes decode and detect, the device searches).
    """

    device: torch.device
    cores: int
    threads: ThreadSetting = AUTO_THREADS
    decode: str = "auto"

    def __post_init__(self) -> None:
        if self.decode not in DECODE_CHOICES:
            raise FRInputError(f"--decode: expected one of {', '.join(DECODE_CHOICES)}, got {self.decode!r}")

    @classmethod
    def resolve(cls, device: "str | torch.device | DevicePolicy" = "cpu",
                threads: "str | int | None" = None, decode: str = "auto") -> "DevicePolicy":
        """The policy of ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:1"``, a torch.device or a
        policy); :class:`~fr_torch.errors.FRInputError` (one line) when it cannot run fR.
        ``threads``: see :attr:`threads` (None = ``$FR_THREADS``, else ``auto``; a policy keeps its own);
        ``decode``: see :attr:`decode`."""
        if isinstance(device, DevicePolicy):
            return device
        return cls(resolve_device(device), usable_cores(), cls._threads(threads), decode)

    @classmethod
    def parse(cls, device: "str | torch.device" = "cpu", threads: "str | int | None" = None) -> "DevicePolicy":
        """The policy of ``device`` without checking that this machine has it: for planning work
        that runs elsewhere (a Ray cluster's GPU nodes).  A malformed name is an FRInputError."""
        try:
            torch_device = torch.device(device)
        except (RuntimeError, TypeError, ValueError):
            raise FRInputError(f"--device: unknown device {device!r} (use cpu or cuda)") from None
        return cls(torch_device, usable_cores(), cls._threads(threads))

    @staticmethod
    def _threads(threads: "str | int | None") -> ThreadSetting:
        if threads is None:
            return parse_threads(os.environ.get(THREADS_ENV), THREADS_ENV)
        return parse_threads(threads, "threads")

    @property
    def on_cpu(self) -> bool:
        return self.device.type == "cpu"

    @property
    def whole_image_workers(self) -> bool:
        """True when worker processes should calibrate whole images (CPU); False when they only
        decode and detect while this process searches on the device (GPU)."""
        return self.on_cpu

    @property
    def default_detector(self) -> str:
        """The detector an estimator uses when its caller names none (:data:`DEFAULT_DETECTOR`)."""
        return DEFAULT_DETECTOR.get(self.device.type, DEFAULT_DETECTOR["cpu"])

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
        """A command's process-wide settings: torch's intra-op threads and OpenCV's threads at most
        :attr:`cores` (in a container both count the host's cores, not the CPUs the quota grants,
        and an OpenMP region with more threads than CPUs stalls on every op); a fixed
        :attr:`threads` count becomes torch's; with ``auto`` the load monitor starts now, so that
        the first search already has a window of the load to go by."""

        if isinstance(self.threads, int):
            torch.set_num_threads(min(self.threads, self.cores))
        elif torch.get_num_threads() > self.cores:
            torch.set_num_threads(self.cores)
        if cv2.getNumThreads() > self.cores:
            cv2.setNumThreads(self.cores)
        if self.threads == AUTO_THREADS and self.on_cpu:

            cpuload.process_monitor().others_busy()

    def search_thread_count(self) -> int | None:
        """Intra-op threads for a search starting now, or None to leave torch's count.  Never more
        than torch's count in effect (a command sets it, :meth:`apply_threads`; worker processes run
        with one) nor :attr:`cores`: a fixed :attr:`threads` caps it; ``auto`` takes
        :func:`threads_for_free_cores` of the cores other processes leave free
        (:func:`fr_torch.runtime.cpuload.process_monitor`); None on a GPU or with ``torch``."""
        if not self.on_cpu or self.threads == TORCH_THREADS:
            return None
        ceiling = min(torch.get_num_threads(), self.cores)
        if isinstance(self.threads, int):
            return min(self.threads, ceiling)
        if ceiling <= 1:
            return None

        return threads_for_free_cores(cpuload.process_monitor().free_cores(), ceiling)

    @contextlib.contextmanager
    def search_threads(self) -> Iterator[None]:
        """Run the enclosed search with :meth:`search_thread_count` intra-op threads, restoring
        torch's count on exit (the library leaves the caller's process settings as they were)."""
        count = self.search_thread_count()
        previous = torch.get_num_threads()
        if count is None or count == previous:
            yield
            return
        torch.set_num_threads(count)
        try:
            yield
        finally:
            torch.set_num_threads(previous)
