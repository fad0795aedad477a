"""The numeric environment (studies.numerics): what it sets, where, and that a user's own
setting stands."""

import os
import subprocess
import sys

from studies import numerics

ZEN4 = {"fpu", "sse2", "avx", "avx2", "fma", "avx512f", "avx512vl"}


def test_defaults_by_machine():
    base = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    # x86 with AVX2 and FMA: the AVX2 code, numpy's targets by the names of its version
    d = numerics.reproducible_defaults(machine="x86_64", flags=ZEN4, numpy_version="2.4.6")
    assert d == {**base, "OPENBLAS_CORETYPE": "Haswell",
                 "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR"}
    d = numerics.reproducible_defaults(machine="AMD64", flags=ZEN4, numpy_version="2.2.1")
    assert d["NPY_DISABLE_CPU_FEATURES"].split()[:2] == ["AVX512F", "AVX512_SKX"]
    d = numerics.reproducible_defaults(machine="x86_64", flags=ZEN4, numpy_version="dev")
    assert d["NPY_DISABLE_CPU_FEATURES"] == "X86_V4 AVX512_ICL AVX512_SPR"
    # no AVX2 (Haswell kernels would not run), or not x86: the CPU's own code
    assert numerics.reproducible_defaults(machine="x86_64", flags={"sse2", "avx"}) == base
    assert numerics.reproducible_defaults(machine="x86_64", flags={"avx2"}) == base
    assert numerics.reproducible_defaults(machine="aarch64", flags={"avx2", "fma"}) == base


def test_cpu_flags_reads_the_flags_line(tmp_path):
    f = tmp_path / "cpuinfo"
    f.write_text("processor\t: 0\nmodel name\t: X\nflags\t\t: fpu avx2 fma\n\n"
                 "processor\t: 1\nflags\t\t: fpu avx2 fma\n")
    assert numerics.cpu_flags(str(f)) == {"fpu", "avx2", "fma"}
    assert numerics.cpu_flags(str(tmp_path / "none")) == frozenset()
    # the model name from the same list (bench rows name their machine by it)
    assert numerics.cpu_model(str(f)) == "X"
    assert numerics.cpuinfo_field("flags", str(tmp_path / "none")) is None
    assert numerics.cpu_model(str(tmp_path / "none"))  # platform's name instead


def test_apply_keeps_what_the_environment_sets():
    env = {"OPENBLAS_NUM_THREADS": "4", "OPENBLAS_CORETYPE": "Zen"}
    done = numerics.apply(env)
    assert env["OPENBLAS_NUM_THREADS"] == "4" and env["OPENBLAS_CORETYPE"] == "Zen"
    assert env["OMP_NUM_THREADS"] == "1" and "OPENBLAS_NUM_THREADS" not in done
    assert set(done) == set(numerics.reproducible_defaults()) - {"OPENBLAS_NUM_THREADS",
                                                                 "OPENBLAS_CORETYPE"}


def test_the_command_sets_them_before_numpy_loads():
    """In a process started without them, ``testbed`` sets the defaults before numpy's
    import, which reads them: numpy's AVX-512 targets are then off where the machine has
    them (and nothing changes where it has not)."""
    code = ("import os; from studies.cli import main; main(['scenes']); import numpy; "
            "from numpy._core._multiarray_umath import __cpu_features__ as f; "
            "print('ENV', os.environ.get('OPENBLAS_CORETYPE'), f.get('X86_V4', False))")
    names = set(numerics.reproducible_defaults())
    env = {k: v for k, v in os.environ.items() if k not in names}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    want = numerics.reproducible_defaults().get("OPENBLAS_CORETYPE")
    assert f"ENV {want} False" in out.stdout, out.stdout
