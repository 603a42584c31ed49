"""A pure tensor function replayed as a CUDA graph, for loops of many small kernels.

A rollout of the point robot launches some 50 kernels a step, each a microsecond of GPU work
behind several of host-side dispatch and launching; replaying the whole rollout as one CUDA graph
leaves the GPU work alone. :class:`GraphedCall` does it for a function of tensors that keeps to
what a graph can hold: tensors in, a dict of tensors out, shapes fixed by the inputs', no host
synchronization (``.item()``, ``bool(tensor)``) inside.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

Signature = tuple[tuple[torch.Size, torch.dtype, torch.device], ...]


class GraphedCall:
    """``fn(*inputs)`` replayed as one CUDA graph per input signature (shapes, dtypes, devices).

    The first call of a signature runs ``fn`` eagerly and returns that result; the graph is then
    captured (after a warm-up on a side stream, as torch asks) under a forked RNG, so neither
    draws from the run's stream. A later call copies its inputs into the graph's, replays it and
    returns copies of its outputs. Random draws inside a graph are torch's graph-safe ones: a
    replay draws what the eager call would from the generator's state, and advances it as much
    (``tests/test_devices.py`` checks the two equal, bit for bit). A graph holds its own memory
    pool for as long as this object lives.
    """

    def __init__(self, fn: Callable[..., dict[str, Tensor]]) -> None:
        self.fn = fn
        self._graphs: dict[Signature, tuple[torch.cuda.CUDAGraph, list[Tensor],
                                            dict[str, Tensor]]] = {}

    def __call__(self, *inputs: Tensor) -> dict[str, Tensor]:
        signature = tuple((t.shape, t.dtype, t.device) for t in inputs)
        captured = self._graphs.get(signature)
        if captured is None:
            result = self.fn(*inputs)
            self._graphs[signature] = self._capture(inputs)
            return result
        graph, static_inputs, static_outputs = captured
        for static, value in zip(static_inputs, inputs):
            static.copy_(value)
        graph.replay()
        return {key: value.clone() for key, value in static_outputs.items()}

    def _capture(self, inputs: tuple[Tensor, ...]
                 ) -> tuple[torch.cuda.CUDAGraph, list[Tensor], dict[str, Tensor]]:
        device = inputs[0].device
        static_inputs = [t.clone() for t in inputs]
        with torch.random.fork_rng(devices=[device]):
            side = torch.cuda.Stream(device)
            side.wait_stream(torch.cuda.current_stream(device))
            with torch.cuda.stream(side):
                self.fn(*static_inputs)
            torch.cuda.current_stream(device).wait_stream(side)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                static_outputs = self.fn(*static_inputs)
        return graph, static_inputs, static_outputs
