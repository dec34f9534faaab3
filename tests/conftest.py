import os

# Tests compare against analytic values and other implementations at float32 tolerances.
os.environ.setdefault("JAX_PLATFORMS", "cpu")
