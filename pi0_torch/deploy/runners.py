"""What runs an exported graph: onnxruntime for ONNX (numpy in and out; no torch), AOTInductor's loader for a `pt2`
package (torch only). Each takes the graph's inputs in `deploy.json`'s order as numpy arrays and returns the actions."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from pi0_torch.deploy.folder import INPUT_NAMES, ExportFolderError

Runner = Callable[[Sequence[np.ndarray]], np.ndarray]
ONNX_PROVIDERS = {
    "cpu": ("CPUExecutionProvider",),
    "cuda": ("CUDAExecutionProvider", "CPUExecutionProvider"),
    "tensorrt": ("TensorrtExecutionProvider", "CUDAExecutionProvider", "CPUExecutionProvider"),
}


def check_provider(fmt: str, provider: str) -> None:
    """Refuse, in one line, a provider that cannot run a graph of format `fmt`."""
    if fmt == "onnx" and provider not in ONNX_PROVIDERS:
        raise ExportFolderError(f"provider must be one of {sorted(ONNX_PROVIDERS)}, got {provider!r}")
    if fmt == "pt2" and provider not in ("cpu", "cuda"):
        raise ExportFolderError(f"an AOTInductor package runs on 'cpu' or 'cuda' (what it was compiled for), not {provider!r}")


def load_runner(path: Path, fmt: str, provider: str = "cpu", threads: int | None = None,
                input_names: Sequence[str] = INPUT_NAMES) -> Runner:
    """A callable running the graph at `path` (`fmt` "onnx" or "pt2") on `provider` ("cpu", "cuda", or for ONNX
    "tensorrt"); `threads`: intra-op threads (None: the runtime's default); `input_names`: the graph's inputs, in the
    order the callable takes them."""
    check_provider(fmt, provider)
    if fmt == "onnx":
        return _onnx_runner(path, provider, threads, tuple(input_names))
    return _pt2_runner(path, provider, threads)


def _onnx_runner(path: Path, provider: str, threads: int | None, input_names: tuple[str, ...]) -> Runner:
    if importlib.util.find_spec("onnxruntime") is None:
        raise ExportFolderError(f"{path.name} needs onnxruntime: pip install 'pi0-torch[deploy]' (or onnxruntime-gpu for "
                                "the CUDA and TensorRT providers)")
    import onnxruntime

    wanted = ONNX_PROVIDERS[provider]
    available = onnxruntime.get_available_providers()
    if wanted[0] not in available:
        raise ExportFolderError(f"this onnxruntime ({onnxruntime.__version__}) has no {wanted[0]} (it has "
                                f"{', '.join(available)}): install onnxruntime-gpu for 'cuda' / 'tensorrt', or use provider 'cpu'")
    options = onnxruntime.SessionOptions()
    if threads is not None:
        options.intra_op_num_threads = threads
    try:
        session = onnxruntime.InferenceSession(str(path), options, providers=[p for p in wanted if p in available])
    except Exception as error:  # onnxruntime raises its own classes (a newer opset, a damaged file)
        text = " ".join(str(error).split())[:300]
        raise ExportFolderError(f"onnxruntime {onnxruntime.__version__} cannot load {path}: {text} (a newer onnxruntime, "
                                "or export again with an --opset it takes)") from None
    names = [item.name for item in session.get_inputs()]
    if set(names) - set(input_names):  # (fed by name: an exporter may drop an input the graph never reads)
        raise ExportFolderError(f"{path}: the graph takes inputs {names}; expected {list(input_names)}")

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        feed = {name: value for name, value in zip(input_names, inputs) if name in names}
        return np.asarray(session.run(None, feed)[0], np.float32)

    return run


def _pt2_runner(path: Path, provider: str, threads: int | None) -> Runner:
    if importlib.util.find_spec("torch") is None:
        raise ExportFolderError(f"{path.name} is an AOTInductor package, which needs torch (pip install torch), the "
                                "version it was compiled with; an ONNX export runs without torch")
    import torch

    if threads is not None:
        torch.set_num_threads(threads)
    try:
        compiled = torch._inductor.aoti_load_package(str(path))
    except Exception as error:  # (a package of another torch version, or for another device)
        raise ExportFolderError(f"torch {torch.__version__} cannot load {path}: {' '.join(str(error).split())[:300]} "
                                "(load it with the torch version and device it was exported with)") from None
    device = torch.device(provider)

    def run(inputs: Sequence[np.ndarray]) -> np.ndarray:
        with torch.inference_mode():
            outputs = compiled(*(torch.from_numpy(np.ascontiguousarray(value)).to(device) for value in inputs))
        actions = outputs[0] if isinstance(outputs, (list, tuple)) else outputs
        return actions.float().cpu().numpy()

    return run
