"""The OpenBLAS kernel pin (covnet.blas_kernel): the same bits on every x86-64 host."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from covnet import blas_kernel


def _child(code: str, **env: str) -> str:
    e = {k: v for k, v in os.environ.items() if k != "OPENBLAS_CORETYPE"} | env
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=e, check=True
    )
    return out.stdout.strip()


needs_avx2 = pytest.mark.skipif(
    not blas_kernel._NEEDS <= blas_kernel._cpu_flags(), reason="not an x86-64 CPU with AVX2/FMA"
)


@needs_avx2
def test_importing_covnet_first_pins_the_kernel_for_the_process_and_its_children():
    code = (
        "import os, subprocess, sys, covnet, numpy; from covnet import blas_kernel; "
        "print(blas_kernel.kernel(), os.environ['OPENBLAS_CORETYPE'])"
    )
    assert _child(code) == f"{blas_kernel.PINNED} {blas_kernel.PINNED}"


def test_a_users_setting_is_kept():
    code = "import os, covnet; print(os.environ['OPENBLAS_CORETYPE'])"
    assert _child(code, OPENBLAS_CORETYPE="Prescott") == "Prescott"


def test_too_late_once_numpy_is_loaded():
    code = "import numpy, os, covnet; print(os.environ.get('OPENBLAS_CORETYPE'))"
    assert _child(code) == "None"


def test_the_kernel_in_use_is_recorded_in_run_json(tmp_path):
    from covnet.runs.rundir import read_json, record_end

    record_end(tmp_path, "completed", "test")
    assert read_json(tmp_path / "run.json")["blas_kernel"] == blas_kernel.kernel()


_THREADS = (
    "import ctypes, pathlib, numpy; "
    "libs = pathlib.Path(numpy.__file__).parent.parent / 'numpy.libs'; "
    "lib = ctypes.CDLL(str(sorted(libs.glob('libscipy_openblas*.so*'))[0])); "
    "print(lib.scipy_openblas_get_num_threads64_())"
)


def _has_openblas_threads_call() -> bool:
    try:
        return _child(_THREADS, OPENBLAS_NUM_THREADS="2") == "2"
    except (subprocess.CalledProcessError, IndexError):
        return False


def test_importing_covnet_first_gives_openblas_one_thread_unless_the_user_says():
    if not _has_openblas_threads_call():
        pytest.skip("NumPy's OpenBLAS does not say its thread count here")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    code = "import covnet; " + _THREADS
    run = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    assert run.stdout.strip() == "1"
    assert _child(code, OPENBLAS_NUM_THREADS="2") == "2"  # the user's number is kept
