"""Where a run's tensors live: one ``--device`` for every command that computes.

``auto`` is CUDA when torch sees a CUDA device, else the CPU. Nothing below the engine picks a
device by itself: functions follow the device of the tensors they are given.

``python -m exploregs_plugin.runtime.device`` says what this machine's torch, CUDA and gsplat will and
will not do (for example after ``pip install -e ".[gpu]"`` on a machine without a GPU).
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import re
import shutil
from typing import Any

import torch

DEVICE_HELP = "auto (CUDA when available, else CPU), cpu, cuda or cuda:N"


class DeviceError(ValueError):
    """A --device value that this machine cannot honour."""


def resolve_device(name: str | torch.device) -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` -> a torch.device this machine has.

    Raises :class:`DeviceError` with a one-line reason (unknown name, no CUDA, no such GPU).
    """
    if isinstance(name, torch.device):
        name = str(name)
    text = str(name).strip().lower()
    if text == "auto":
        return torch.device("cuda") if torch.cuda.is_available() else torch.device("cpu")
    if text == "cpu":
        return torch.device("cpu")
    match = re.fullmatch(r"cuda(?::(\d+))?", text)
    if match is None:
        raise DeviceError(f"--device {name!r} is not a device; choose {DEVICE_HELP}")
    if not torch.cuda.is_available():
        build = f"built with CUDA {torch.version.cuda}" if torch.version.cuda else "a CPU-only build"
        raise DeviceError(f"--device {text}: no CUDA device is available here (torch {torch.__version__}, "
                          f"{build}); use --device cpu or auto")
    index = int(match.group(1)) if match.group(1) is not None else None
    if index is not None and index >= torch.cuda.device_count():
        raise DeviceError(f"--device {text}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    return torch.device(text)


def to_device(value: Any, device: torch.device) -> Any:
    """``value`` with every tensor inside (dicts, lists, tuples) moved to ``device``."""
    if isinstance(value, torch.Tensor):
        return value.to(device)
    if isinstance(value, dict):
        return {k: to_device(v, device) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(to_device(v, device) for v in value)
    return value


def make_generator(device: torch.device, seed: int) -> torch.Generator:
    """A generator on ``device`` (random draws must come from a generator on their device)."""
    return torch.Generator(device=device).manual_seed(int(seed))


def restore_generator(generator: torch.Generator, state: torch.Tensor) -> bool:
    """Load a saved generator state. A state saved on another device type (a CPU run resumed on
    CUDA, or back) has another format: the generator is then reseeded from that state, so the run
    stays deterministic from here on but not bit-identical to an uninterrupted run. Returns
    whether the state was taken as it was."""
    try:
        generator.set_state(state)
        return True
    except RuntimeError:
        digest = hashlib.sha256(state.to(torch.uint8).cpu().numpy().tobytes()).digest()
        generator.manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))
        return False


def machine_report() -> list[str]:
    """What this machine can run, one line per part: torch's build and CUDA devices, what
    ``--device auto`` picks, and whether gsplat's CUDA kernels (``--model.raster.backend gsplat``)
    can run here. Imports nothing beyond torch (gsplat is looked up, not imported)."""
    cuda = torch.cuda.is_available()
    if cuda:
        names = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
        build = f"CUDA {torch.version.cuda} build; CUDA devices: {names}"
    elif torch.version.cuda:
        build = f"CUDA {torch.version.cuda} build, but no CUDA device is visible"
    else:
        build = "a CPU-only build, so no CUDA device can be used"
    lines = [f"torch {torch.__version__}: {build}", f"--device auto: {resolve_device('auto')}"]
    try:
        version = importlib.metadata.version("gsplat")
    except importlib.metadata.PackageNotFoundError:
        lines.append('gsplat: not installed; only --model.raster.backend gsplat (CUDA) needs it: pip install -e ".[gpu]"')
        return lines
    if not cuda:
        lines.append(f"gsplat {version}: installed, but it will not run here: its kernels are CUDA-only and this "
                     f"machine has no CUDA device; every command renders on the CPU with the other backends, and "
                     f"--model.raster.backend gsplat is refused with one line")
        return lines
    cuda_home = os.environ.get("CUDA_HOME") or os.environ.get("CUDA_PATH")
    nvcc = (shutil.which("nvcc", path=os.path.join(cuda_home, "bin")) if cuda_home else None) or shutil.which("nvcc")
    if nvcc is None:
        where = f"CUDA_HOME={cuda_home} has no bin/nvcc" if cuda_home else "no nvcc on PATH and CUDA_HOME is unset"
        lines.append(f"gsplat {version}: installed; it compiles its CUDA kernels on first use and needs nvcc for that "
                     f"({where}): install the CUDA toolkit or use --model.raster.backend torch")
    else:
        lines.append(f"gsplat {version}: installed; --model.raster.backend gsplat compiles its CUDA kernels on first "
                     f"use with {nvcc} (a few minutes, once; MAX_JOBS=N bounds the parallel compile)")
    return lines


if __name__ == "__main__":
    print("\n".join(machine_report()))
