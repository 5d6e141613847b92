"""Replay of a captured CUDA graph: the fast inference path of a policy on a GPU.

At batch size 1 a new action chunk is a few hundred small kernels (one U-Net pass per sampler step);
launched one by one from Python the GPU waits for the host most of the time. Captured once into a CUDA
graph they launch as one unit. Written here because PyTorch's ``make_graphed_callables`` is for training
(it captures a backward pass too) and ``torch.compile(mode="reduce-overhead")`` needs a compiler toolchain
and a long warm-up at run time.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

import torch
from torch import Tensor


class CapturedCall:
    """``fn(*inputs) -> Tensor`` captured for inputs of one shape; calling it replays the graph.

    ``fn`` must be free of host synchronisation and of randomness (pass noise in as an input). The inputs
    are copied into static buffers the graph reads; the output is a fresh copy of the graph's output.
    """

    def __init__(self, fn: Callable[..., Tensor], inputs: tuple[Tensor, ...], warmup: int = 2):
        self.inputs = tuple(x.detach().clone() for x in inputs)
        # warm-up on a side stream (cuBLAS handles and workspaces must exist before capture)
        stream = torch.cuda.Stream(device=self.inputs[0].device)
        stream.wait_stream(torch.cuda.current_stream(self.inputs[0].device))
        with torch.cuda.stream(stream):
            for _ in range(warmup):
                fn(*self.inputs)
        torch.cuda.current_stream(self.inputs[0].device).wait_stream(stream)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.output = fn(*self.inputs)

    def __call__(self, *inputs: Tensor) -> Tensor:
        for static, x in zip(self.inputs, inputs, strict=True):
            static.copy_(x)
        self.graph.replay()
        return self.output.clone()


class GraphCache:
    """The last ``size`` captured calls by key (e.g. batch size and sampler steps); older ones are freed."""

    def __init__(self, size: int = 4):
        self.size = size
        self._calls: OrderedDict[Hashable, tuple[Any, CapturedCall]] = OrderedDict()

    def get(self, key: Hashable, owner: Any, fn: Callable[..., Tensor], inputs: tuple[Tensor, ...]) -> CapturedCall:
        """The call captured for ``key``; captured anew when missing or when ``owner`` (whatever the graph
        reads besides its inputs, e.g. the weight constants it was captured with) is not the same object."""
        hit = self._calls.get(key)
        if hit is not None and hit[0] is owner:
            self._calls.move_to_end(key)
            return hit[1]
        self._calls.pop(key, None)
        call = CapturedCall(fn, inputs)
        self._calls[key] = (owner, call)  # holding owner keeps the memory the graph reads alive
        while len(self._calls) > self.size:
            self._calls.popitem(last=False)
        return call

    def clear(self) -> None:
        self._calls.clear()

    def __deepcopy__(self, memo: dict) -> GraphCache:
        return GraphCache(self.size)  # graphs are bound to their buffers: a copy captures its own

    def __getstate__(self) -> dict:
        return {"size": self.size, "_calls": OrderedDict()}
