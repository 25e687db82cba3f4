"""One OpenBLAS kernel on every x86_64 machine, so that srl computes the same bits on any of them.

The learning loop is chaotic in its last digits: the critic's fits go through OpenBLAS (numpy,
scipy), and OpenBLAS picks its kernels by the CPU at load time. An AVX-512 kernel (an Intel Xeon)
rounds differently from the AVX2 one (an AMD EPYC): the paper loop's weights after 150 steps of
rlq at N = 6 differed by 0.29 between the two, the same code and packages. Pinning the Haswell
kernel (AVX2 and FMA, which every x86_64 CPU of the last decade has) gives both the same bits, and
costs nothing measurable on srl's small matrices. ``OPENBLAS_CORETYPE`` must be set before numpy,
scipy or casadi load OpenBLAS, which reads it once: ``import common`` sets it (every srl module
imports it first); a user's value is kept."""

from __future__ import annotations

import os
import platform
from collections.abc import MutableMapping

KERNEL = "Haswell"
NEEDS = {"avx2", "fma"}  # the Haswell kernel's instructions


def cpu_flags(cpuinfo: str = "/proc/cpuinfo") -> set[str]:
    """The first CPU's flags (Linux), none if unreadable."""
    try:
        with open(cpuinfo) as text:
            for line in text:
                if line.startswith("flags"):
                    return set(line.partition(":")[2].split())
    except OSError:
        pass
    return set()


def pin_openblas_kernel(
    environ: MutableMapping[str, str] = os.environ, machine: str | None = None, cpuinfo: str = "/proc/cpuinfo"
) -> str | None:
    """Set ``OPENBLAS_CORETYPE`` to the Haswell kernel on an x86_64 CPU that runs it, unless it is
    set; returns the value set (None: left as it was)."""
    if "OPENBLAS_CORETYPE" in environ or (machine or platform.machine()) not in ("x86_64", "AMD64"):
        return None
    if not NEEDS.issubset(cpu_flags(cpuinfo)):
        return None
    environ["OPENBLAS_CORETYPE"] = KERNEL
    return KERNEL
