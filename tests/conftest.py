import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Orthogonal initialisation runs LAPACK QR through OpenBLAS, whose worker threads spin badly when the two cores
# are shared with XLA (0.004 s -> 1.6 s per QR); one thread is plenty for these small matrices.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# The suite runs with the XLA:CPU settings of the command-line tools (512-bit vectors on AVX-512 CPUs), chosen
# here before any test starts JAX; importing tgrf_jax alone leaves XLA_FLAGS untouched.
import tgrf_jax  # noqa: E402

tgrf_jax.configure_cpu()


# Many tests compile the same programs (the tiny training chunk, the evaluation; in-process and in CLI
# subprocesses). They share a persistent compilation cache that lives for one pytest invocation: created empty by
# the first process, inherited by the xdist workers and the CLI subprocesses through the environment, deleted at
# the end, so no test depends on what an earlier invocation left and nothing is written to the user's ~/.cache.
# A cached executable is the very program that was compiled: every number is the same as without the cache.
# Set TGRF_JAX_COMPILE_CACHE yourself (e.g. "off") to override.
_OWNED_CACHE = None


def pytest_configure(config):
    global _OWNED_CACHE
    if "TGRF_JAX_COMPILE_CACHE" not in os.environ:
        _OWNED_CACHE = tempfile.mkdtemp(prefix="tgrf-jax-tests-")
        os.environ["TGRF_JAX_COMPILE_CACHE"] = _OWNED_CACHE
    from tgrf_jax import compile_cache

    compile_cache.enable()


def pytest_unconfigure(config):
    if _OWNED_CACHE is not None:
        shutil.rmtree(_OWNED_CACHE, ignore_errors=True)
