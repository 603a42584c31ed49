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
from importlib import metadata
from pathlib import Path

import torch

from armeta_rl.errors import ConfigError

CPU = torch.device("cpu")
DEVICE_FORMS = "cpu, cuda, cuda:N"
_NAME = re.compile(r"cpu|cuda(:\d+)?")
CPUINFO = Path("/proc/cpuinfo")
CPUINFO_BYTES = 1 << 16
"""How much of ``/proc/cpuinfo`` :func:`cpu_model` reads: the first processor's block is at its
start."""


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


def cpu_model(cpuinfo: Path = CPUINFO) -> str:
    r"""The processor as Linux names it: ``model name``, then vendor family, model and stepping
    (a model name such as "Intel(R) Xeon(R) Processor" can stand for several generations);
    ``"unknown CPU"`` where ``cpuinfo`` cannot be read (another OS) or names no model.

    >>> import tempfile
    >>> with tempfile.TemporaryDirectory() as d:
    ...     info = Path(d) / "cpuinfo"
    ...     _ = info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\n"
    ...                         "model\t\t: 207\nmodel name\t: Intel(R) Xeon(R) Processor\n"
    ...                         "stepping\t: 2\n\nprocessor\t: 1\nmodel\t\t: 85\n")
    ...     cpu_model(info)
    'Intel(R) Xeon(R) Processor, family 6 model 207 stepping 2'
    """
    try:
        with cpuinfo.open("rb") as file:
            text = file.read(CPUINFO_BYTES).decode(errors="replace")
    except OSError:
        return "unknown CPU"
    first = text.split("\n\n", 1)[0]
    fields = dict(line.split(":", 1) for line in first.splitlines() if ":" in line)
    fields = {key.strip(): value.strip() for key, value in fields.items()}
    name = fields.get("model name", "unknown CPU")
    ids = [f"{label} {fields[key]}" for key, label in
           (("cpu family", "family"), ("model", "model"), ("stepping", "stepping"))
           if key in fields]
    return ", ".join([name, " ".join(ids)]) if ids else name


def machine_name(device: torch.device) -> str:
    """What a run's numbers depend on besides its seed and config: the processor (on the CPU,
    torch's kernel level too: AVX2 and AVX512 kernels round differently, so one seed's results
    differ between machines), the GPU a ``cuda`` device names, and the torch and MuJoCo versions.
    Every evaluation report records it, so results from different machines are told apart."""
    hardware = f"{cpu_model()} ({torch.backends.cpu.get_cpu_capability()})"
    if device.type == "cuda":
        hardware = f"{torch.cuda.get_device_name(device)} with {hardware}"
    return f"{hardware}; torch {torch.__version__}, mujoco {metadata.version('mujoco')}"
