import gc
import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Orthogonal initialisation runs LAPACK QR through OpenBLAS, whose worker threads spin badly when the two cores
# are shared with XLA (0.004 s -> 1.6 s per QR); one thread is plenty for these small matrices.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# The suite runs with the XLA:CPU settings of the command-line tools (512-bit vectors on AVX-512 CPUs), chosen
# here before any test starts JAX; importing tgrf_jax alone leaves XLA_FLAGS untouched.
import pytest  # noqa: E402

import tgrf_jax  # noqa: E402

tgrf_jax.configure_cpu()

# The suite checks behaviour, not the speed of generated code (benchmarks/ measures that, with XLA's defaults),
# and most of its time is XLA compiling small programs that then run briefly. Without LLVM's optimisation passes
# those compiles are much shorter: the suite takes about a fifth less time. Programs compared with each other (resume,
# sweep against a solo run, determinism) are compiled alike. TGRF_JAX_TEST_XLA_OPT=full keeps XLA's defaults.
OPT_FLAG = "--xla_backend_optimization_level"
TEST_XLA_OPT = os.environ.get("TGRF_JAX_TEST_XLA_OPT", "fast")
if TEST_XLA_OPT not in ("fast", "full"):
    raise ValueError(f"TGRF_JAX_TEST_XLA_OPT={TEST_XLA_OPT!r}: allowed 'fast' (the default) or 'full'")
if TEST_XLA_OPT == "fast" and OPT_FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {OPT_FLAG}=0".strip()


# Many tests compile the same programs (the tiny training chunk, the evaluation; in-process and in CLI
# subprocesses). They share a persistent compilation cache that lives for one pytest invocation: created empty by
# the first process, inherited by the xdist workers and the CLI subprocesses through the environment, deleted at
# the end, so no test depends on what an earlier invocation left and nothing is written to the user's ~/.cache.
# A cached executable is the very program that was compiled: every number is the same as without the cache.
# Set TGRF_JAX_COMPILE_CACHE yourself (e.g. "off") to override.
_OWNED_CACHE = None
# The recordings (`tgrf-data fetch`) are looked up in a data directory of the suite's own, empty unless a test
# fills it: a user's downloaded recordings change no test.
_OWNED_DATA = None


def pytest_configure(config):
    global _OWNED_CACHE, _OWNED_DATA
    if _OWNED_DATA is None:
        _OWNED_DATA = tempfile.mkdtemp(prefix="tgrf-jax-tests-data-")
        os.environ["TGRF_JAX_DATA"] = _OWNED_DATA
    if getattr(config.option, "loadscopereorder", False):
        config.option.loadscopereorder = False  # keep the order of pytest_collection_modifyitems below
    if "TGRF_JAX_COMPILE_CACHE" not in os.environ:
        _OWNED_CACHE = tempfile.mkdtemp(prefix="tgrf-jax-tests-")
        os.environ["TGRF_JAX_COMPILE_CACHE"] = _OWNED_CACHE
    from tgrf_jax.runtime import compile_cache

    compile_cache.enable()


def pytest_unconfigure(config):
    for owned in (_OWNED_CACHE, _OWNED_DATA):
        if owned is not None:
            shutil.rmtree(owned, ignore_errors=True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop each module's compiled programs when it ends. Every loaded XLA:CPU executable keeps memory mappings
    of its code, and an xdist worker that runs hundreds of tests otherwise accumulates them up to the kernel's
    limit (vm.max_map_count, 65,530 by default), where the next compile or cache access crashes the worker."""
    yield
    import jax

    jax.clear_caches()
    gc.collect()


# Test modules, longest first (their summed --durations in CI); modules not listed follow in pytest's order.
# `--dist loadscope` hands each worker one module at a time in collection order, and by default first reorders the
# modules by their number of tests, which leaves the few long training modules for last: one worker then runs
# them alone while the other has nothing left to do. Longest first lets the short modules fill the end.
LONGEST_FIRST = (
    "test_crowds.py",
    "test_ppo.py",
    "test_sweep.py",
    "test_scenario_cli.py",
    "test_search_experiment.py",
    "test_gym.py",
    "test_deploy.py",
    "test_tune.py",
    "test_lidar_policies.py",
    "test_orca_obstacles.py",
    "test_env.py",
    "test_sensing_noise.py",
    "test_orca.py",
    "test_notebooks.py",
    "test_shards.py",
    "test_routing_env.py",
    "test_replay.py",
    "test_predictor_train.py",
    "test_evaluate.py",
    "test_reproduce.py",
    "test_nets.py",
    "test_predictor_env.py",
    "test_curves.py",
    "test_train_cli.py",
    "test_render.py",
    "test_lock.py",
    "test_properties.py",
    "test_frames.py",
    "test_batching.py",
    "test_compile_cache.py",
    "test_bad_inputs.py",
    "test_predictor_parity.py",
    "test_pretrained.py",
    "test_cpu.py",
)


def pytest_collection_modifyitems(session, config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: each module keeps its own order
