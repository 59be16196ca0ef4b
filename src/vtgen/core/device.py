"""Where torch work runs and in which precision: the device and precision named in params."""

from __future__ import annotations

from pathlib import Path

import torch

CPU_BF16_FLAGS = ("avx512_bf16", "amx_bf16")  # /proc/cpuinfo flags of CPUs with bf16 arithmetic in hardware


def resolve_device(name: str) -> torch.device:
    """auto -> CUDA when available else CPU; cuda without a GPU is an error, not a silent fallback."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("translation.device is 'cuda' but torch sees no CUDA device (use auto or cpu)")
    return torch.device(name)


def cpu_flags(cpuinfo: Path = Path("/proc/cpuinfo")) -> set[str]:
    """The CPU feature flags the kernel reports (Linux); empty where that file is absent."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return set()
    for line in text.splitlines():
        if line.startswith("flags"):
            return set(line.partition(":")[2].split())
    return set()


def native_bf16(device: torch.device, flags: set[str] | None = None) -> tuple[bool, str]:
    """(whether ``device`` computes in bf16 in hardware, the evidence). CUDA: torch's check without
    emulation (compute capability 8.0 or later); CPU: an AVX512-BF16 or AMX-BF16 flag among ``flags``
    (default :func:`cpu_flags`). Elsewhere bf16 is emulated and slower than fp32."""
    if device.type == "cuda":
        ok = torch.cuda.is_bf16_supported(including_emulation=False)
        return ok, f"CUDA device {torch.cuda.get_device_name(device)} {'has' if ok else 'lacks'} native bf16"
    if device.type == "cpu":
        found = sorted(set(CPU_BF16_FLAGS) & (cpu_flags() if flags is None else flags))
        return (True, f"CPU flags {', '.join(found)}") if found else \
            (False, f"CPU lacks {' and '.join(CPU_BF16_FLAGS)} (bf16 would be emulated)")
    return False, f"no native bf16 check for device type {device.type}"


def resolve_precision(name: str, device: torch.device, flags: set[str] | None = None) -> tuple[str, str]:
    """(fp32 or bf16, why): ``auto`` picks bf16 where :func:`native_bf16` holds, else fp32; fp32 and bf16
    are taken as given (a bf16 request without native support is kept, with a warning in the reason)."""
    if name not in ("auto", "fp32", "bf16"):
        raise ValueError(f"unknown precision '{name}' (allowed: auto, fp32, bf16)")
    native, evidence = native_bf16(device, flags)
    if name == "auto":
        return ("bf16" if native else "fp32"), f"auto: {evidence}"
    if name == "bf16" and not native:
        return "bf16", f"as set; warning: {evidence}, so bf16 is likely slower than fp32 here"
    return name, "as set"
