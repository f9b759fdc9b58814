"""Runtime fixes that let stock nerfstudio 1.1.5 train, load and render offline on a CPU.

:func:`install` is idempotent and is called by every nerfuser_ns command and by the plugin's method
configs (which nerfstudio imports when ``ns-train``/``ns-render``/``ns-eval``/``ns-viewer`` start), so
installing the plugin is enough. It does four things:

1. LPIPS becomes lazy and optional. nerfstudio models build torchmetrics' LPIPS in ``populate_modules``,
   which downloads AlexNet weights and dies offline. The replacement builds the real metric on first use
   only if the weights are already in the torch hub cache, and otherwise returns NaN with one warning.
2. nerfstudio checkpoints load under torch >= 2.6 (``weights_only=True`` by default): the numpy types they
   hold are added to torch's safe globals, so no arbitrary pickle code is allowed. Older torch (no
   ``add_safe_globals`` before 2.4) loads them as is: its default is ``weights_only=False``.
3. The CPU fast path: the torch hash encoding, memory-bound on CPU, runs through ``torch.compile`` (inductor
   fuses it into C++ loops: ~20x rendering, ~30x training here). CUDA inputs and tcnn keep the stock path, and so
   does a torch where ``torch.compile`` cannot run or compile this (torch < 2.0, a platform or Python dynamo does
   not support, inductor's C++ build not importable, a failing forward or backward compile: one warning).
   Disable with ``NERFUSER_CPU_FAST_PATH=0`` or ``install(fast_path=False)``.
4. On a machine without CUDA, glibc's allocator keeps freed blocks of up to 32 MiB in the heap instead of returning
   them to the system (``mallopt``: the mmap and trim thresholds). Rendering allocates and frees chunk-sized tensors
   for every ray batch; glibc otherwise maps each one afresh, and the kernel's page faults on that memory took a
   third of the render time here (identical renders, ~1.4x faster). Other C libraries, and machines with CUDA, are
   left as they are. Disable with ``NERFUSER_MALLOC_TUNING=0`` (read once, when the runtime is installed).
"""

from __future__ import annotations

import ctypes
import importlib
import os
import sys
import warnings
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

# What these fixes patch (torchmetrics' LPIPS, nerfstudio's hash encoding, numpy's pickle types, dynamo) is imported
# inside the functions that patch it: nerfstudio's method discovery imports this module, which must stay cheap and
# must not import nerfstudio modules before the patches are in place.

_FAST_PATH_ENV = "NERFUSER_CPU_FAST_PATH"
_MALLOC_ENV = "NERFUSER_MALLOC_TUNING"
# glibc's mallopt parameters (malloc.h) and the largest mmap threshold it accepts on 64-bit (HEAP_MAX_SIZE / 2)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_MMAP_THRESHOLD_MAX = 32 * 1024 * 1024
_TRIM_THRESHOLD = 1024 * 1024 * 1024
_installed = False
_fast_path_enabled = True
_fast_path_broken = False
_compiled_hash_fwd: Any = None
# encodings whose compiled backward ran, per input requires_grad (see _probe_backward)
_probed: weakref.WeakKeyDictionary[nn.Module, set[bool]] = weakref.WeakKeyDictionary()
_lpips_warned = False

# torchvision's AlexNet weights, as torchmetrics' LPIPS requests them.
_ALEXNET_WEIGHTS = "alexnet-owt-7be5be79.pth"


def install(fast_path: bool | None = None) -> None:
    """Apply the offline/CPU runtime fixes (idempotent).

    Args:
        fast_path: force the CPU fast path on or off; None reads ``NERFUSER_CPU_FAST_PATH`` (default on).
    """
    global _installed
    set_fast_path(fast_path)
    if _installed:
        return
    # nerfstudio 1.1.5 indexes with lists on every camera-ray call; torch warns each time and buries the output
    warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
    _allow_nerfstudio_checkpoints()
    _make_lpips_lazy()
    _patch_hash_encoding()
    tune_allocator()
    _installed = True


def tune_allocator(enabled: bool | None = None) -> bool:
    """Make glibc keep freed blocks up to 32 MiB for reuse (see the module docstring, item 4).

    Args:
        enabled: force on or off; None reads ``NERFUSER_MALLOC_TUNING`` (default on) and skips machines with CUDA.

    Returns True when both thresholds were set; False when disabled, with CUDA, or where glibc's ``mallopt`` is
    not available (other platforms and C libraries).
    """
    if enabled is None:
        enabled = _env_flag(_MALLOC_ENV) and not torch.cuda.is_available()
    return bool(enabled) and set_malloc_thresholds(_MMAP_THRESHOLD_MAX, _TRIM_THRESHOLD)


def set_malloc_thresholds(mmap_bytes: int, trim_bytes: int) -> bool:
    """Set glibc's mmap and trim thresholds (``mallopt``); True when both were accepted, False where the platform or
    C library has no ``mallopt`` (it is this process-wide setting's one writer, for the runtime and the kit's
    memory sampler alike)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # musl and other libcs have no mallopt
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    # mallopt returns 1 on success
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_bytes)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_bytes))


ON_WORDS, OFF_WORDS = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
"""What the ``NERFUSER_*`` on/off environment switches read as on and as off (lower case)."""


def _env_flag(name: str) -> bool:
    """An on/off environment switch, on unless set to one of :data:`OFF_WORDS` (a runtime switch never stops a run)."""
    return os.environ.get(name, "1").strip().lower() not in OFF_WORDS


def set_fast_path(enabled: bool | None) -> None:
    """Turn the compiled CPU hash encoding on or off at run time (None: from the environment)."""
    global _fast_path_enabled
    if enabled is None:
        enabled = _env_flag(_FAST_PATH_ENV)
    _fast_path_enabled = bool(enabled)


def fast_path_enabled() -> bool:
    return _fast_path_enabled and not _fast_path_broken


# --- checkpoints ---------------------------------------------------------------------------------------------


def _allow_nerfstudio_checkpoints() -> None:
    """nerfstudio saves numpy scalars (e.g. in scheduler state); allow exactly those types."""
    if not hasattr(torch.serialization, "add_safe_globals"):  # torch < 2.4: torch.load is not weights_only
        return
    safe: list[Any] = [np.dtype, np.ndarray]
    try:
        from numpy._core.multiarray import _reconstruct, scalar  # numpy >= 2
    except ImportError:  # pragma: no cover - numpy 1.x
        from numpy.core.multiarray import _reconstruct, scalar  # type: ignore[no-redef]
    safe += [scalar, _reconstruct]
    safe += [type(np.dtype(t)) for t in ("float16", "float32", "float64", "int32", "int64", "uint8", "bool")]
    torch.serialization.add_safe_globals(safe)


def load_checkpoint(path: Path) -> dict[str, Any]:
    """Load a nerfstudio checkpoint on the CPU, with a one-line error naming the file when it is unusable."""
    install()
    try:
        state = torch.load(path, map_location="cpu")
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: checkpoint not found") from None
    except Exception as e:  # noqa: BLE001 - any unpickling failure is the file's fault
        raise ValueError(f"{path}: not a loadable nerfstudio checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(state, dict) or "pipeline" not in state:
        raise ValueError(f"{path}: not a nerfstudio checkpoint (no 'pipeline' entry)")
    return state


# --- LPIPS ---------------------------------------------------------------------------------------------------


def lpips_weights_available() -> bool:
    """True when torchmetrics' LPIPS can be built without the network (AlexNet weights cached locally)."""
    return (Path(torch.hub.get_dir()) / "checkpoints" / _ALEXNET_WEIGHTS).is_file()


class LazyLPIPS(nn.Module):
    """Drop-in for torchmetrics' ``LearnedPerceptualImagePatchSimilarity`` that never touches the network.

    The real metric is built on first call if its weights are cached locally; otherwise every call returns NaN
    and one warning says LPIPS is unavailable. It holds no parameters, so checkpoints stay LPIPS-free; stock
    nerfstudio loads them anyway (its pipeline falls back to non-strict loading for the missing LPIPS keys).
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__()
        self._args = args
        self._kwargs = kwargs
        self._metric: list[nn.Module] = []  # a list keeps the real metric out of state_dict()
        self._unavailable = False

    def forward(self, preds: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        global _lpips_warned
        if not self._metric and not self._unavailable:
            if lpips_weights_available():
                # here: the real class only once its weights are known to be on disk
                from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity as _Real

                self._metric.append(_Real(*self._args, **self._kwargs))
            else:
                self._unavailable = True
        if self._unavailable:
            if not _lpips_warned:
                warnings.warn(
                    f"LPIPS unavailable: AlexNet weights are not in {Path(torch.hub.get_dir()) / 'checkpoints'} "
                    "and nerfuser_ns never downloads; LPIPS is reported as NaN.",
                    stacklevel=2,
                )
                _lpips_warned = True
            return torch.tensor(float("nan"), device=preds.device)
        metric = self._metric[0].to(preds.device)
        return metric(preds, target)


def _make_lpips_lazy() -> None:
    import torchmetrics.image.lpip as lpip_module  # here: only install() patches it

    # nerfstudio models import the class inside populate_modules, so replacing the module attribute suffices.
    lpip_module.LearnedPerceptualImagePatchSimilarity = LazyLPIPS  # type: ignore[misc,assignment]
    try:
        import torchmetrics.image as image_module

        image_module.LearnedPerceptualImagePatchSimilarity = LazyLPIPS  # type: ignore[misc,assignment]
    except (ImportError, AttributeError):  # pragma: no cover
        pass


# --- CPU fast path -------------------------------------------------------------------------------------------


def _patch_hash_encoding() -> None:
    # here: nerfstudio's field modules load only when install() patches them
    from nerfstudio.field_components.encodings import HashEncoding

    if getattr(HashEncoding, "_nerfuser_patched", False):
        return
    stock_forward = HashEncoding.forward

    def forward(self: HashEncoding, in_tensor: torch.Tensor) -> torch.Tensor:
        if self.tcnn_encoding is not None or in_tensor.device.type != "cpu" or not fast_path_enabled():
            return stock_forward(self, in_tensor)
        return _run_compiled(self, in_tensor, stock_forward)

    HashEncoding.forward = forward  # type: ignore[method-assign]
    HashEncoding._nerfuser_patched = True  # type: ignore[attr-defined]
    HashEncoding._nerfuser_stock_forward = stock_forward  # type: ignore[attr-defined]


def _run_compiled(module: nn.Module, in_tensor: torch.Tensor, stock_forward: Any) -> torch.Tensor:
    global _compiled_hash_fwd, _fast_path_broken
    if in_tensor.shape[:-1].numel() == 0:
        return stock_forward(module, in_tensor)
    if _compiled_hash_fwd is None:
        from nerfstudio.field_components.encodings import HashEncoding  # here: see _patch_hash_encoding

        reason = _compile_unusable_reason()
        if reason is not None:
            _fast_path_broken = True
            warnings.warn(
                f"nerfuser_ns CPU fast path disabled, {reason}; using the stock hash encoding "
                f"(set {_FAST_PATH_ENV}=0 to silence this).",
                stacklevel=2,
            )
            return stock_forward(module, in_tensor)
        # One compiled function for every instance: dynamo treats module parameters as inputs, and dynamic
        # shapes avoid a recompile per ray-batch size.
        _compiled_hash_fwd = torch.compile(HashEncoding.pytorch_fwd, dynamic=True)
    try:
        _probe_backward(module, in_tensor)
        return _compiled_hash_fwd(module, in_tensor)
    except Exception as e:  # noqa: BLE001 - no C++ compiler, unsupported platform...: fall back, once, loudly
        _fast_path_broken = True
        warnings.warn(
            f"nerfuser_ns CPU fast path disabled, torch.compile failed ({type(e).__name__}: {str(e)[:200]}); "
            f"using the stock hash encoding (set {_FAST_PATH_ENV}=0 to skip the attempt).",
            stacklevel=2,
        )
        return stock_forward(module, in_tensor)


def _probe_backward(module: nn.Module, in_tensor: torch.Tensor) -> None:
    """Compile (and run) the backward of a new graph now, on a detached copy of the input, where a failure is caught.

    torch compiles a graph's backward lazily, inside ``loss.backward()``, beyond the reach of :func:`_run_compiled`'s
    fallback. torch 2.1's inductor, for one, fails there with dynamic shapes once the positions require grad (as
    nerfacto's field always makes them). One probe per encoding and input mode (the graphs dynamo keeps apart); the
    copy has the input's shape, strides and ``requires_grad``, so the real call reuses the probed graphs.
    """
    if not torch.is_grad_enabled():
        return
    params = [p for p in module.parameters() if p.requires_grad]
    if not params and not in_tensor.requires_grad:
        return
    probed = _probed.setdefault(module, set())
    if in_tensor.requires_grad in probed:
        return
    x = in_tensor.detach().requires_grad_(in_tensor.requires_grad)
    y = _compiled_hash_fwd(module, x)
    torch.autograd.grad(y.float().sum(), params + ([x] if x.requires_grad else []), allow_unused=True)
    probed.add(in_tensor.requires_grad)


_FAST_PATH_MIN_TORCH = (2, 2)
"""Oldest torch whose compile of the hash encoding is not known to fail (2.1.2 fails; 2.11 and 2.13 measured)."""


def _torch_version() -> tuple[int, int]:
    major, minor = torch.__version__.split(".")[:2]
    return int(major), int("".join(c for c in minor if c.isdigit()) or 0)


def _compile_unusable_reason() -> str | None:
    """Why ``torch.compile`` cannot run in this process (None: it may; a failure at compile time is caught later)."""
    if not callable(getattr(torch, "compile", None)):
        return f"torch {torch.__version__} has no torch.compile (torch >= 2.0 needed)"
    if _torch_version() < _FAST_PATH_MIN_TORCH:
        # measured on 2.1.2: inductor's backward of the hash encoding with dynamic shapes fails (AssertionError)
        return f"torch {torch.__version__}'s inductor cannot compile the hash encoding's backward (torch >= 2.2 needed)"
    try:
        from torch._dynamo.eval_frame import check_if_dynamo_supported  # here: a private module, may move
    except ImportError:  # pragma: no cover - a torch that moved it: let the compile attempt decide
        return None
    try:
        check_if_dynamo_supported()  # raises on a platform or Python version this torch's dynamo does not support
    except Exception as e:  # noqa: BLE001
        return f"torch.compile is not supported here ({type(e).__name__}: {str(e)[:200]})"
    try:
        importlib.import_module("torch.utils.cpp_extension")  # inductor builds its CPU kernels through it
    except ImportError as e:
        # torch 2.1 (at least) imports setuptools' pkg_resources there, which setuptools >= 82 no longer ships
        hint = "; pip install 'setuptools<82'" if "pkg_resources" in str(e) else ""
        return f"inductor cannot build C++ here ({type(e).__name__}: {str(e)[:200]}{hint})"
    return None
