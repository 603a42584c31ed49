"""The torch device a run computes on: the config key ``device`` (``cpu``, ``cuda``, ``cuda:N``).

:func:`resolve_device` is the one place a device name becomes a ``torch.device``; the builders of
:mod:`armeta_rl.factory` hand the result down as an argument. Leaders, the task distributions
(p0 and the flow adversary), the torch-native collectors and their envs, and evaluation run on it;
MuJoCo envs step on the CPU, and an episode collector moves the policy's parameters to its env
for the rollout and the trajectories back (docs/scale.md, "Devices").
"""

from __future__ import annotations

import re
from contextlib import AbstractContextManager

import torch

from armeta_rl.errors import ConfigError

CPU = torch.device("cpu")
DEVICE_FORMS = "cpu, cuda, cuda:N"
_NAME = re.compile(r"cpu|cuda(:\d+)?")


def is_device_name(name: str) -> bool:
    """Whether ``name`` has one of the accepted forms (``cpu``, ``cuda``, ``cuda:N``), whatever
    this machine has."""
    return _NAME.fullmatch(name) is not None


def resolve_device(name: str, key: str = "device") -> torch.device:
    """The ``torch.device`` named ``name``, checked against this machine.

    Raises:
        ConfigError: naming ``key``, for another form, ``cuda`` without a CUDA device, or
            ``cuda:N`` beyond the devices present; the message lists what this machine allows.
    """
    if not isinstance(name, str) or not is_device_name(name):
        raise ConfigError(key, name, f"allowed: {DEVICE_FORMS}")
    if name == "cpu":
        return CPU
    count = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if count == 0:
        raise ConfigError(key, name, "CUDA is not available here (no CUDA device, or a torch "
                                     "built without CUDA); allowed here: cpu")
    device = torch.device(name)
    if device.index is not None and device.index >= count:
        here = ", ".join(["cpu", "cuda", *(f"cuda:{i}" for i in range(count))])
        raise ConfigError(key, name, f"this machine has {count} CUDA device"
                                     f"{'s' if count > 1 else ''}; allowed here: {here}")
    return device


def forked_rng(device: torch.device) -> AbstractContextManager[None]:
    """``torch.random.fork_rng`` over the CPU generator and, on CUDA, the device's own: what runs
    inside (an evaluation under its own seed) leaves the run's random streams as they were."""
    if device.type != "cuda":
        return torch.random.fork_rng(devices=[])
    index = torch.cuda.current_device() if device.index is None else device.index
    return torch.random.fork_rng(devices=[index], device_type="cuda")
