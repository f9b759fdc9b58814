"""The offline/CPU runtime: compiled hash grid equals the stock one, LPIPS never downloads, checkpoints load."""

from __future__ import annotations

import math
import platform
import socket
import sys
import warnings

import numpy as np
import pytest
import torch
from nerfstudio.field_components.encodings import HashEncoding

from nerfuser_ns import runtime


@pytest.fixture
def fast_path_restored():
    yield
    runtime.set_fast_path(None)


def test_fast_path_matches_stock_forward_and_backward(fast_path_restored):
    runtime.install()
    torch.manual_seed(0)
    enc = HashEncoding(num_levels=6, log2_hashmap_size=12, max_res=256, implementation="torch")
    x = torch.rand(5000, 3)

    runtime.set_fast_path(False)
    y_stock = enc(x)
    (g_stock,) = torch.autograd.grad(y_stock.square().sum(), enc.hash_table)

    runtime.set_fast_path(True)
    reason = runtime._compile_unusable_reason()
    if reason is not None:  # a torch that cannot compile it (e.g. 2.1): the stock path, said once, same numbers
        said_before = runtime._fast_path_broken  # the fallback warns once per process
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            y_fallback = enc(x)
        assert not runtime.fast_path_enabled()
        assert said_before or any(reason in str(w.message) for w in caught), [str(w.message) for w in caught]
        torch.testing.assert_close(y_fallback, y_stock, rtol=0, atol=0)
        return
    y_fast = enc(x)
    (g_fast,) = torch.autograd.grad(y_fast.square().sum(), enc.hash_table)
    assert runtime.fast_path_enabled(), "torch.compile failed on this machine"

    torch.testing.assert_close(y_fast, y_stock, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(g_fast, g_stock, rtol=1e-4, atol=1e-5)
    # a different batch size and a batched shape reuse the dynamic-shape compile and still agree
    x2 = torch.rand(3, 77, 3)
    runtime.set_fast_path(False)
    y2_stock = enc(x2)
    runtime.set_fast_path(True)
    torch.testing.assert_close(enc(x2), y2_stock, rtol=1e-5, atol=1e-6)


def test_fast_path_switch_reads_environment(monkeypatch, fast_path_restored):
    monkeypatch.setenv("NERFUSER_CPU_FAST_PATH", "0")
    runtime.set_fast_path(None)
    assert not runtime.fast_path_enabled()
    monkeypatch.setenv("NERFUSER_CPU_FAST_PATH", "1")
    runtime.set_fast_path(None)
    # on, unless this process already found that its torch cannot compile it (then the stock path, whatever is asked)
    assert runtime.fast_path_enabled() is not runtime._fast_path_broken


def test_lpips_is_lazy_and_offline(monkeypatch, tmp_path):
    """nerfstudio's models build LPIPS in populate_modules; offline that must neither download nor fail."""
    runtime.install()
    monkeypatch.setattr(runtime, "_lpips_warned", False)  # it warns once per process: an earlier test may have
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))  # an empty hub cache: no weights

    def no_network(*args, **kwargs):
        raise AssertionError("LPIPS tried to reach the network")

    monkeypatch.setattr(socket.socket, "connect", no_network)
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    metric = LearnedPerceptualImagePatchSimilarity(normalize=True)
    assert not runtime.lpips_weights_available()
    assert len(list(metric.parameters())) == 0 and metric.state_dict() == {}
    img = torch.rand(1, 3, 16, 16)
    with pytest.warns(UserWarning, match="LPIPS unavailable"):
        value = metric(img, img)
    assert math.isnan(float(value))


def test_checkpoint_with_numpy_scalars_loads_under_weights_only(tmp_path):
    runtime.install()
    path = tmp_path / "step-000000001.ckpt"
    state = {"step": 1, "pipeline": {"_model.w": torch.ones(2)}, "scalers": {"scale": np.float64(2.0)}}
    torch.save(state, path)
    loaded = runtime.load_checkpoint(path)
    assert loaded["scalers"]["scale"] == 2.0 and torch.equal(loaded["pipeline"]["_model.w"], torch.ones(2))


def test_bad_checkpoints_give_one_line_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.ckpt"):
        runtime.load_checkpoint(tmp_path / "missing.ckpt")
    garbage = tmp_path / "garbage.ckpt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="garbage.ckpt: not a loadable nerfstudio checkpoint"):
        runtime.load_checkpoint(garbage)
    other = tmp_path / "other.ckpt"
    torch.save({"weights": torch.ones(1)}, other)
    with pytest.raises(ValueError, match="no 'pipeline' entry"):
        runtime.load_checkpoint(other)


class _FakeMallopt:
    """glibc's mallopt as ctypes gives it: a callable that takes argtypes/restype and records its calls."""

    def __init__(self, result: int):
        self.calls: list[tuple[int, int]] = []
        self.result = result

    def __call__(self, param: int, value: int) -> int:
        self.calls.append((param, value))
        return self.result


class _FakeLibc:
    def __init__(self, result: int = 1):
        self.mallopt = _FakeMallopt(result)


@pytest.mark.parametrize("env, cuda, expected", [("1", False, True), ("0", False, False), ("1", True, False)])
def test_allocator_tuning_follows_environment_and_device(monkeypatch, env, cuda, expected):
    fake = _FakeLibc()
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: fake)
    monkeypatch.setattr(runtime.sys, "platform", "linux")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: cuda)
    monkeypatch.setenv("NERFUSER_MALLOC_TUNING", env)
    assert runtime.tune_allocator() is expected
    # glibc's M_MMAP_THRESHOLD (-3) at its 64-bit maximum, M_TRIM_THRESHOLD (-1) above it, or nothing at all
    assert fake.mallopt.calls == ([(-3, 32 * 1024 * 1024), (-1, 1024 * 1024 * 1024)] if expected else [])


def test_allocator_tuning_reports_a_refusal_and_other_platforms(monkeypatch):
    monkeypatch.setattr(runtime.ctypes, "CDLL", lambda name: _FakeLibc(result=0))
    monkeypatch.setattr(runtime.sys, "platform", "linux")
    assert runtime.tune_allocator(True) is False  # glibc refused a value
    monkeypatch.setattr(runtime.sys, "platform", "darwin")
    assert runtime.tune_allocator(True) is False

    def no_mallopt(name):
        raise AttributeError("mallopt")

    monkeypatch.setattr(runtime.sys, "platform", "linux")
    monkeypatch.setattr(runtime.ctypes, "CDLL", no_mallopt)
    assert runtime.tune_allocator(True) is False


def test_allocator_tuning_sets_real_glibc_thresholds():
    """The real mallopt accepts both values on Linux with glibc (a value glibc refused would make it False)."""
    expected = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert runtime.tune_allocator(True) is expected
