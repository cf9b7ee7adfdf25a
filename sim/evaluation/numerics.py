"""The numerical kernels an evaluation's figures depend on to the last bit, pinned for its workers.

The targets' guidance has knife edges (which side of an obstacle a target takes can turn on the
last bit of a QP solution: docs/RESULTS.md, "Reproducing a figure"), so a last-bit difference
anywhere in the arithmetic gives another truth in some trials. Two libraries choose their
kernels by the CPU they load on: OpenBLAS (numpy's and scipy's matrix products, solves and
factorisations) takes AVX-512 kernels where the CPU has them, and numpy dispatches some of its
own loops to AVX-512 too. Both round differently from their AVX2 kernels, and each moves the
figures of a trial (docs/RESULTS.md, "Reproducing a figure", has them).

So the evaluation's worker processes load both libraries with the AVX2 kernels
(``pin_kernels``) on every x86-64 CPU that has AVX2 and FMA: the same figures there whatever
else the CPU has. Elsewhere (another architecture, or an x86-64 without AVX2) nothing is pinned
and some trials differ. A variable the user set already is left as it is.
"""
from __future__ import annotations

import contextlib
import os
import platform

# numpy >= 2.4 names its AVX-512 dispatch targets X86_V4, AVX512_ICL, AVX512_SPR; earlier numpy
# AVX512F, AVX512_SKX, ...: a name a numpy does not know is ignored (an ImportWarning, hidden)
NUMPY_AVX512 = ("X86_V4 AVX512_ICL AVX512_SPR AVX512F AVX512CD AVX512_KNL AVX512_KNM AVX512_SKX "
                "AVX512_CLX AVX512_CNL")
PINNED = {"OPENBLAS_CORETYPE": "Haswell", "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512}


def _cpu_features() -> dict:
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:  # numpy 1.x
        from numpy.core._multiarray_umath import __cpu_features__
    return __cpu_features__


def can_pin() -> bool:
    """The AVX2 kernels run here: x86-64 with AVX2 and FMA."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return False
    f = _cpu_features()
    return bool(f.get("AVX2") and f.get("FMA3"))


def pin_kernels(environ=None) -> bool:
    """Set the variables that make OpenBLAS and numpy load their AVX2 kernels in processes
    started from now on with ``environ`` (default os.environ; read at numpy's import, so this
    process's own numpy is not affected). True when pinned; variables already set stay."""
    env = os.environ if environ is None else environ
    if not can_pin():
        return False
    for name, value in PINNED.items():
        env.setdefault(name, value)
    return True


def kernels_description(environ=None) -> str:
    """What the workers load: the pinned kernels, or the CPU's own."""
    env = os.environ if environ is None else environ
    if env.get("OPENBLAS_CORETYPE") == PINNED["OPENBLAS_CORETYPE"] and \
            env.get("NPY_DISABLE_CPU_FEATURES") == PINNED["NPY_DISABLE_CPU_FEATURES"]:
        return "kernels pinned to AVX2 (OpenBLAS Haswell, numpy without AVX-512)"
    chosen = {k: env[k] for k in PINNED if k in env}
    return "the CPU's own kernels" + (f" ({', '.join(f'{k}={v}' for k, v in chosen.items())})" if chosen else "")


def _cpu_model() -> str:
    with contextlib.suppress(OSError):
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown CPU"


def numerics_description() -> str:
    """The CPU, the numerical packages and the kernels a run's figures depend on to the last bit."""
    from importlib.metadata import PackageNotFoundError, version

    import numpy as np

    def ver(pkg):
        try:
            return version(pkg)
        except PackageNotFoundError:
            return "absent"

    blas = "unknown BLAS"
    with contextlib.suppress(Exception):
        b = np.show_config(mode="dicts")["Build Dependencies"]["blas"]
        blas = f"{b['name']} {b['version']}"
    pkgs = ", ".join(f"{p} {ver(p)}" for p in ("numpy", "scipy", "daqp", "osqp"))
    return f"{_cpu_model()}; {pkgs}; {blas}; {kernels_description()}"
