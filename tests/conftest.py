import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Orthogonal initialisation runs LAPACK QR through OpenBLAS, whose worker threads spin badly when the two cores
# are shared with XLA (0.004 s -> 1.6 s per QR); one thread is plenty for these small matrices.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
# The command-line tools keep a persistent compilation cache in ~/.cache; tests call them in-process and must
# neither write there nor depend on what an earlier run left (tests/test_compile_cache.py switches it on).
os.environ.setdefault("TGRF_JAX_COMPILE_CACHE", "off")

# The suite runs with the XLA:CPU settings of the command-line tools (512-bit vectors on AVX-512 CPUs), chosen
# here before any test starts JAX; importing tgrf_jax alone leaves XLA_FLAGS untouched.
import tgrf_jax  # noqa: E402

tgrf_jax.configure_cpu()
