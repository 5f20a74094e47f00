"""The fused ops of a sampling step as `torch.library` custom ops (`torch.ops.pi0_torch.*`): each is one op on the
meta device and to `torch.compile`, and its kernel launches record in a CUDA graph like any other.

Each op runs its Triton kernel (`pi0_torch.kernels.triton_kernels`) where `triton_reason` finds none against it (a
CUDA tensor and an importable triton, or `TRITON_INTERPRET=1`), else its torch reference
(`pi0_torch.kernels.reference`). `call` (the one way the engine calls an op) goes through the dispatcher only where
something has to see the op itself (a dispatch mode such as the op counter or FakeTensor, or compiling): a custom
op's dispatch costs 20-70 µs of host time per call, more than the kernel it launches.

(No `from __future__ import annotations` here: `torch.library.custom_op` reads the schema from the annotations.)
"""

import functools
import importlib.util
import logging
import os
import sys
from types import ModuleType
from typing import Any, Callable, List, Optional

import torch
from torch.utils._python_dispatch import _get_current_dispatch_mode

from pi0_torch.kernels import reference
from pi0_torch.utils.triton_guard import set_aside_broken_triton

logger = logging.getLogger(__name__)

TRITON_KERNELS, PERSISTENT = "pi0_torch.kernels.triton_kernels", "pi0_torch.kernels.persistent"  # the Triton modules


@functools.lru_cache(maxsize=None)
def _triton_import_error() -> Optional[str]:
    if (broken := set_aside_broken_triton()) is not None:
        return broken
    if importlib.util.find_spec("triton") is None:
        return "triton is not installed (torch's CUDA wheels bring it; pip install 'pi0-torch[kernels]')"
    try:
        from pi0_torch.kernels import persistent, triton_kernels  # noqa: F401  (compiles nothing: kernels JIT on first launch)
    except Exception as error:  # an incompatible triton
        return f"the installed triton does not load the kernels ({type(error).__name__}: {error})"
    return None


@functools.lru_cache(maxsize=None)
def _interpreter_error() -> Optional[str]:
    """Why triton's interpreter cannot run the kernels here (None: it can), found by running one of them: triton
    3.6's interpreter turns a loop's tensor bound into a Python int with `int(array)`, which numpy 2.4 refuses for
    the one-element arrays it holds (numpy 2.3 and older only warn; triton 3.9's squeezes the array first). Nothing
    to find where the kernels were compiled rather than interpreted (TRITON_INTERPRET set after their import:
    `benchmarks/kernel_resources.py`)."""
    from pi0_torch.kernels import triton_kernels

    if not triton_kernels.INTERPRETING:
        return None
    try:
        triton_kernels.matmul_residual_(torch.zeros(2, 16), torch.ones(2, 16), torch.ones(16, 16), None)
    except Exception as error:
        import numpy
        import triton

        return (f"triton {triton.__version__}'s interpreter cannot run the kernels with numpy {numpy.__version__} "
                f"({type(error).__name__}: {str(error)[:200]}; triton 3.6's runs them with numpy < 2.4)")
    return None


def triton_reason(device: torch.device) -> Optional[str]:
    """Why the Triton kernels cannot run on `device` (None: they can): a CUDA device and an importable triton, or
    any device under `TRITON_INTERPRET=1` (triton's interpreter, for tests on the CPU) where the interpreter runs
    them (`_interpreter_error`)."""
    if device.type == "cuda":
        return _triton_import_error()
    if os.environ.get("TRITON_INTERPRET") != "1":
        return f"the fused kernels are written for CUDA, not {device.type}"
    return _triton_import_error() or _interpreter_error()


@functools.lru_cache(maxsize=None)
def _home(name: str, device: torch.device) -> tuple[ModuleType, bool]:
    """The module of op `name`'s implementation for tensors on `device`, and whether it launches on a GPU: its Triton
    kernels' where `triton_reason` finds nothing against them (`_triton_import_error` imported them), else the torch
    references. Decided once per op and device: what decides it (the device, the installed triton,
    `TRITON_INTERPRET`, read by triton when the kernels are defined) holds for the process."""
    if triton_reason(device) is not None:
        return reference, False
    return sys.modules[PERSISTENT if name == "expert_layers_" else TRITON_KERNELS], device.type == "cuda"


def _dispatched() -> bool:
    """Whether the custom ops themselves must run (through the dispatcher): a dispatch mode (the op counter,
    FakeTensor) or the compiler has to see them."""
    return torch.compiler.is_compiling() or _get_current_dispatch_mode() is not None


def _run(name: str, *args: Any) -> Any:
    """The op `name`'s implementation on `args`, on the GPU of its first tensor: triton launches on the current GPU,
    so a model on cuda:1 while cuda:0 is current makes its GPU current for the launch (its kernels would otherwise
    run on cuda:0, on cuda:0's stream, against cuda:1's memory)."""
    device = args[0].device
    module, on_gpu = _home(name, device)
    implementation = getattr(module, name)
    if on_gpu and device.index != torch.cuda.current_device():
        with torch.cuda.device(device):
            return implementation(*args)
    return implementation(*args)


def call(op: Any, *args: Any) -> Any:
    """Run the custom op `op` (e.g. `call(norm_qkv_rope, ...)`): straight into its implementation, or through the
    dispatcher where a dispatch mode or the compiler has to see it (see the module docstring). The one way the
    engine calls an op: about half a µs of host time on top of the implementation's on the development CPU."""
    if _dispatched():
        return op(*args)
    return _run(_NAMES[op], *args)


def resolved(op: Any, device: torch.device) -> Callable[..., Any]:
    """`call(op, ...)` for a run of calls on `device`'s tensors that nothing can enter in between (the layers of a
    sampling step): what `call` decides per call (the dispatcher or not, the implementation, the GPU to make
    current), decided once."""
    if _dispatched():
        return op
    module, on_gpu = _home(_NAMES[op], device)
    if on_gpu and device.index != torch.cuda.current_device():
        return functools.partial(_run, _NAMES[op])
    return getattr(module, _NAMES[op])


def expert_layers_op_by_op_(x: torch.Tensor, *arguments: Any) -> None:
    """`expert_layers_` (same arguments) as five ops per layer, each its kernel: the fused step where the persistent
    kernel is not used (the loop of `reference.expert_layers_`, on the implementations `call` would run)."""
    reference.expert_layers_(x, *arguments, implementations=tuple(
        resolved(op, x.device) for op in (norm_qkv_rope, range_attention, matmul_residual_, norm_gate_up_geglu)))


@torch.library.custom_op("pi0_torch::embed_actions", mutates_args=())
def embed_actions(x_t: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, out_weight: Optional[torch.Tensor],
                  out_bias: Optional[torch.Tensor]) -> torch.Tensor:
    return _run("embed_actions", x_t, weight, bias, out_weight, out_bias)


@embed_actions.register_fake
def _(x_t, weight, bias, out_weight, out_bias):
    columns = weight.shape[1] if out_weight is None else out_weight.shape[1]
    return x_t.new_empty(x_t.shape[0] * x_t.shape[1], columns, dtype=weight.dtype)


@torch.library.custom_op("pi0_torch::add_layer_norm_", mutates_args=("residual",))
def add_layer_norm_(residual: torch.Tensor, y: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float) -> torch.Tensor:
    return _run("add_layer_norm_", residual, y, weight, bias, eps)


@add_layer_norm_.register_fake
def _(residual, y, weight, bias, eps):
    return torch.empty_like(residual)


@torch.library.custom_op("pi0_torch::norm_qkv_rope", mutates_args=("key_cache", "value_cache"))
def norm_qkv_rope(
    x: torch.Tensor, scale: torch.Tensor, bias: Optional[torch.Tensor], weight: torch.Tensor, cos: torch.Tensor,
    sin: torch.Tensor, key_cache: torch.Tensor, value_cache: torch.Tensor, first_slot: int, eps: float,
) -> torch.Tensor:
    return _run("norm_qkv_rope", x, scale, bias, weight, cos, sin, key_cache, value_cache, first_slot, eps)


@norm_qkv_rope.register_fake
def _(x, scale, bias, weight, cos, sin, key_cache, value_cache, first_slot, eps):
    head_dim = key_cache.shape[-1]
    return x.new_empty(x.shape[0], weight.shape[1] - 2 * head_dim)


@torch.library.custom_op("pi0_torch::norm_gate_up_geglu", mutates_args=())
def norm_gate_up_geglu(x: torch.Tensor, scale: torch.Tensor, bias: Optional[torch.Tensor], weight: torch.Tensor, eps: float) -> torch.Tensor:
    return _run("norm_gate_up_geglu", x, scale, bias, weight, eps)


@norm_gate_up_geglu.register_fake
def _(x, scale, bias, weight, eps):
    return x.new_empty(x.shape[0], weight.shape[1] // 2)


@torch.library.custom_op("pi0_torch::matmul_residual_", mutates_args=("residual",))
def matmul_residual_(residual: torch.Tensor, y: torch.Tensor, weight: torch.Tensor, gate: Optional[torch.Tensor]) -> None:
    _run("matmul_residual_", residual, y, weight, gate)


@matmul_residual_.register_fake
def _(residual, y, weight, gate):
    return None


@torch.library.custom_op("pi0_torch::range_attention", mutates_args=())
def range_attention(query: torch.Tensor, key_cache: torch.Tensor, value_cache: torch.Tensor, first: torch.Tensor,
                    row_ends: torch.Tensor) -> torch.Tensor:
    return _run("range_attention", query, key_cache, value_cache, first, row_ends)


@range_attention.register_fake
def _(query, key_cache, value_cache, first, row_ends):
    batch, tokens, heads, head_dim = query.shape
    return query.new_empty(batch * tokens, heads * head_dim)


@torch.library.custom_op("pi0_torch::norm_linear_euler_", mutates_args=("x_t",))
def norm_linear_euler_(x_t: torch.Tensor, tokens: torch.Tensor, scale: torch.Tensor, bias: torch.Tensor,
                       weight: torch.Tensor, dt: float, eps: float) -> None:
    _run("norm_linear_euler_", x_t, tokens, scale, bias, weight, dt, eps)


@norm_linear_euler_.register_fake
def _(x_t, tokens, scale, bias, weight, dt, eps):
    return None


@torch.library.custom_op("pi0_torch::rope_cache_write", mutates_args=("key_cache", "value_cache"))
def rope_cache_write(qkv: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor, key_cache: torch.Tensor,
                     value_cache: torch.Tensor, first_slot: int, slot: Optional[torch.Tensor] = None) -> torch.Tensor:
    return _run("rope_cache_write", qkv, cos, sin, key_cache, value_cache, first_slot, slot)


@rope_cache_write.register_fake
def _(qkv, cos, sin, key_cache, value_cache, first_slot, slot=None):
    return qkv.new_empty(qkv.shape[0], qkv.shape[1] - 2 * key_cache.shape[-1])


@torch.library.custom_op("pi0_torch::geglu", mutates_args=())
def geglu(gate_up: torch.Tensor) -> torch.Tensor:
    return _run("geglu", gate_up)


@geglu.register_fake
def _(gate_up):
    return gate_up.new_empty(gate_up.shape[0], gate_up.shape[1] // 2)


@torch.library.custom_op("pi0_torch::expert_layers_", mutates_args=("x", "key_cache", "value_cache"))
def expert_layers_(
    x: torch.Tensor, attention_scales: torch.Tensor, qkv: List[torch.Tensor], o: List[torch.Tensor],
    mlp_scales: torch.Tensor, gate_up: List[torch.Tensor], down: List[torch.Tensor], cos: torch.Tensor,
    sin: torch.Tensor, key_cache: torch.Tensor, value_cache: torch.Tensor, first: torch.Tensor, row_ends: torch.Tensor,
    first_slot: int, eps: float, qkv_bias: Optional[torch.Tensor], o_gate: Optional[torch.Tensor],
    gate_up_bias: Optional[torch.Tensor], down_gate: Optional[torch.Tensor],
) -> None:
    _run("expert_layers_", x, attention_scales, qkv, o, mlp_scales, gate_up, down, cos, sin, key_cache, value_cache,
         first, row_ends, first_slot, eps, qkv_bias, o_gate, gate_up_bias, down_gate)


@expert_layers_.register_fake
def _(x, attention_scales, qkv, o, mlp_scales, gate_up, down, cos, sin, key_cache, value_cache, first, row_ends,
      first_slot, eps, qkv_bias, o_gate, gate_up_bias, down_gate):
    return None


def op_name(op: Any) -> str:
    """A custom op's name (`pi0_torch::geglu` -> `geglu`): its functions' in `reference` and the Triton modules."""
    return op._name.split("::")[-1]


_NAMES: dict[Any, str] = {op: op_name(op) for op in (  # (for `call`)
    embed_actions, add_layer_norm_, norm_qkv_rope, norm_gate_up_geglu, matmul_residual_, range_attention,
    norm_linear_euler_, rope_cache_write, geglu, expert_layers_)}
