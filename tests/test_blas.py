"""srl pins OpenBLAS's kernel on x86_64 (common/system/blas.py) so that its figures are the same
bits on any CPU: set where it applies, left alone where it does not, and in effect in srl's
processes (the snapshot provenance test, tests/test_bench_actor.py, reproduces 150 chaotic steps
that an AVX-512 kernel changed)."""

from __future__ import annotations

import os
from pathlib import Path

from common.system.blas import KERNEL, pin_openblas_kernel


def cpuinfo(tmp_path: Path, flags: str) -> str:
    path = tmp_path / "cpuinfo"
    path.write_text(f"processor\t: 0\nvendor_id\t: GenuineIntel\nflags\t\t: {flags}\n\nprocessor\t: 1\n")
    return str(path)


def test_the_haswell_kernel_is_pinned_on_an_x86_64_cpu_that_runs_it(tmp_path: Path) -> None:
    env: dict[str, str] = {}
    assert pin_openblas_kernel(env, "x86_64", cpuinfo(tmp_path, "fpu sse2 fma avx avx2 avx512f")) == KERNEL
    assert env == {"OPENBLAS_CORETYPE": "Haswell"}


def test_the_kernel_is_left_alone_where_it_would_not_run_or_the_user_chose(tmp_path: Path) -> None:
    for machine, flags, env in (
        ("x86_64", "fpu sse2 avx", {}),  # no AVX2 / FMA: the Haswell kernel would fault
        ("aarch64", "fp asimd", {}),  # another architecture's kernels
        ("x86_64", "fma avx2", {"OPENBLAS_CORETYPE": "SkylakeX"}),  # the user's choice
        ("x86_64", "fma avx2", None),  # no /proc/cpuinfo: nothing known
    ):
        given = dict(env or {})
        path = cpuinfo(tmp_path, flags) if env is not None else str(tmp_path / "absent")
        assert pin_openblas_kernel(given, machine, path) is None, (machine, flags)
        assert given == (env or {})


def test_srl_processes_run_with_the_pin() -> None:
    # tests/conftest.py imports common first, as every srl process does
    expected = pin_openblas_kernel({}) or os.environ.get("OPENBLAS_CORETYPE")
    assert os.environ.get("OPENBLAS_CORETYPE") == expected
