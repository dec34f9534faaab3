import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Orthogonal initialisation runs LAPACK QR through OpenBLAS, whose worker threads spin badly when the two cores
# are shared with XLA (0.004 s -> 1.6 s per QR); one thread is plenty for these small matrices.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
