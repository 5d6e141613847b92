"""Replay of captured CUDA graphs: the fast paths of a policy on a GPU.

At these model sizes a new action chunk (a few hundred small kernels at batch size 1) and a training step
(~5000 kernels for forward and backward) are bound by launching kernels one by one from Python: the GPU
waits for the host most of the time. Captured once into a CUDA graph they launch as one unit.

Inference uses its own small capture (:class:`CapturedCall`): PyTorch's ``make_graphed_callables`` captures
a backward pass too, and ``torch.compile(mode="reduce-overhead")`` needs a compiler toolchain and a long
warm-up at run time. Training (:class:`TrainGraphs`) uses ``make_graphed_callables``, which is made for it:
forward and backward become two graphs behind one autograd function, so LeRobot's own loop (backward,
gradient clipping, optimizer step) runs unchanged around them.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable
from typing import Any

import torch
from torch import Tensor, nn


class CapturedCall:
    """``fn(*inputs) -> Tensor`` captured for inputs of one shape; calling it replays the graph.

    ``fn`` must be free of host synchronisation and of randomness (pass noise in as an input). The inputs
    are copied into static buffers the graph reads; the output is a fresh copy of the graph's output.
    """

    # "thread_local": another thread's CUDA work during a capture (a live-steering fit beside the control loop
    # allocating memory) neither invalidates the capture nor fails itself, as torch's default "global" makes it
    capture_error_mode = "thread_local"

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
        with torch.cuda.graph(self.graph, capture_error_mode=self.capture_error_mode):
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


class _LossModule(nn.Module):
    """``fn(batch) -> outputs`` with the batch's tensors as positional inputs, as ``make_graphed_callables``
    wants them; ``model`` is a submodule so that its parameters are the graphs' weights."""

    def __init__(self, model: nn.Module, fn: Callable[[dict[str, Tensor]], Any], keys: tuple[str, ...]):
        super().__init__()
        self.model = model
        self._fn = fn
        self.keys = keys

    def forward(self, *tensors: Tensor) -> Any:
        return self._fn(dict(zip(self.keys, tensors, strict=True)))


class TrainGraphs:
    """A training loss ``fn(batch)`` of ``model`` with its forward and backward replayed from CUDA graphs.

    One pair of graphs per batch signature (keys, shapes, dtypes; an epoch's last, smaller batch gets its own)
    and per storage of the model's parameters and buffers (``.to()``, new behaviors: captured anew); the
    last ``size`` are kept. ``fn`` must be free of host synchronisation and draw its randomness from the
    CUDA generator (graph-safe: each replay draws new numbers, the same ones an eager call would from that
    generator state). Outputs are the graphs' static tensors: read them before the next call.
    """

    def __init__(self, size: int = 2, warmup: int = 3):
        self.size = size
        self.warmup = warmup
        self._steps: OrderedDict[Hashable, nn.Module] = OrderedDict()
        self._tensor_dicts: tuple[nn.Module, list[dict]] | None = None  # (model, its modules' tensor dicts)

    def __call__(self, model: nn.Module, fn: Callable[[dict[str, Tensor]], Any], batch: dict[str, Tensor]) -> Any:
        keys = tuple(sorted(batch))
        tensors = tuple(batch[k] for k in keys)
        key = (keys, tuple((tuple(t.shape), t.dtype) for t in tensors), self._storage(model))
        step = self._steps.get(key)
        if step is None:
            step = self._capture(model, fn, keys, tensors)
            self._steps[key] = step
            while len(self._steps) > self.size:
                self._steps.popitem(last=False)
        else:
            self._steps.move_to_end(key)
        return step(*tensors)

    def _storage(self, model: nn.Module) -> tuple:
        """Where the model's parameters and buffers live and which of them train, checked every step: the module
        tree is walked once (``Module.parameters()`` walks it every call, ~1 ms a step for ~250 tensors on a
        CPU), its modules' tensor dicts kept, which show a tensor reassigned or registered later."""
        if self._tensor_dicts is None or self._tensor_dicts[0] is not model:
            self._tensor_dicts = (model, [d for m in model.modules() for d in (m._parameters, m._buffers)])
        return tuple((t.data_ptr(), t.requires_grad) for d in self._tensor_dicts[1] for t in d.values() if t is not None)

    def _capture(self, model: nn.Module, fn: Callable, keys: tuple[str, ...], tensors: tuple[Tensor, ...]) -> nn.Module:
        # The warm-up passes run the loss for real: put back what they changed (running statistics, the
        # generator), so that a graphed training draws the same numbers as an eager one from the same seed.
        device = tensors[0].device
        saved = [(b, b.detach().clone()) for b in model.buffers()]
        rng = torch.cuda.get_rng_state(device)
        module = _LossModule(model, fn, keys).train(model.training)
        inputs = tuple(t.detach().clone() for t in tensors)  # the graphs' static inputs
        graphed = torch.cuda.make_graphed_callables(module, inputs, num_warmup_iters=self.warmup,
                                                    allow_unused_input=True)
        torch.cuda.set_rng_state(rng, device)
        with torch.no_grad():
            for b, value in saved:
                b.copy_(value)
        return graphed

    def clear(self) -> None:
        self._steps.clear()

    def __deepcopy__(self, memo: dict) -> TrainGraphs:
        return TrainGraphs(self.size, self.warmup)

    def __getstate__(self) -> dict:
        return {"size": self.size, "warmup": self.warmup, "_steps": OrderedDict(), "_tensor_dicts": None}
