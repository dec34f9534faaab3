"""The three ways to run one decision: the JAX network jitted, the ONNX file in ONNX Runtime, and the deserialized
StableHLO artifact. Each is a callable on NumPy float32 arrays returning NumPy `(action, new_state)`."""

from __future__ import annotations

import pathlib

import numpy as np

from tgrf_jax.config import ConfigError
from tgrf_jax.deploy.policy import ONNX_FILE, STABLEHLO_FILE, PolicyStep
from tgrf_jax.deploy.source import PolicySource

RUNTIMES = ("jax", "onnx", "stablehlo")


def _need_file(directory, name: str, runtime: str) -> pathlib.Path:
    if directory is None:
        raise ConfigError(
            f"runtime {runtime!r} runs an exported file; load a tgrf-export directory "
            f"(this policy was not exported: run tgrf-export first), or use runtime 'jax'"
        )
    path = pathlib.Path(directory) / name
    if not path.is_file():
        raise ConfigError(
            f"{str(path)!r} does not exist: the export holds no {runtime} file (tgrf-export --format chose others)"
        )
    return path


class JaxRuntime:
    def __init__(self, step: PolicyStep) -> None:
        self._fn = step.jitted()

    def __call__(self, *inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        action, state = self._fn(*inputs)
        return np.asarray(action), np.asarray(state)


class OnnxRuntime:
    def __init__(self, directory: pathlib.Path | None, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError:
            raise ConfigError("runtime 'onnx' needs onnxruntime: pip install 'tgrf-jax[deploy]'") from None
        options = ort.SessionOptions()
        # One decision is a few hundred small ops: a thread pool costs more in hand-offs than it saves.
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        path = _need_file(directory, ONNX_FILE, "onnx")
        try:
            self._session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        except Exception as e:  # ONNX Runtime reports a damaged file as one of its own exception types
            reason = " ".join(str(e).split())[:300]
            raise ConfigError(f"{str(path)!r} is not a loadable ONNX model ({type(e).__name__}: {reason})") from None
        # the file's own input order: policy.INPUT_NAMES, or LIDAR_INPUT_NAMES for a policy that reads a scan
        self._names = [i.name for i in self._session.get_inputs()]

    def __call__(self, *inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if len(inputs) != len(self._names):
            raise ValueError(f"the ONNX policy takes {len(self._names)} inputs {self._names}; got {len(inputs)}")
        action, state = self._session.run(None, dict(zip(self._names, inputs)))
        return action, state


class StableHloRuntime:
    def __init__(self, directory: pathlib.Path | None) -> None:
        import jax

        path = _need_file(directory, STABLEHLO_FILE, "stablehlo")
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
        except Exception as e:  # a damaged file fails deep inside the flatbuffer reader
            raise ConfigError(
                f"{str(path)!r} is not a readable jax.export artifact ({type(e).__name__}: {e})"
            ) from None
        self._fn = jax.jit(exported.call)

    def __call__(self, *inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        action, state = self._fn(*inputs)
        return np.asarray(action), np.asarray(state)


def make_runtime(
    source: PolicySource, runtime: str = "jax", threads: int = 1
) -> JaxRuntime | OnnxRuntime | StableHloRuntime:
    if runtime not in RUNTIMES:
        raise ConfigError(f"unknown runtime {runtime!r}; allowed: {', '.join(RUNTIMES)}")
    if runtime == "jax":
        return JaxRuntime(PolicyStep(source.config, source.params))
    if runtime == "onnx":
        return OnnxRuntime(source.exported_dir, threads)
    return StableHloRuntime(source.exported_dir)
