"""Counting a forward pass op by op at the dispatch level: bytes moved, FLOPs, casts, layouts (issue #53).

Not a benchmark itself (``run_all.py`` skips files whose name starts with ``_``): ``network_traffic.py`` uses it.

Every ATen operation that reaches the dispatcher (under autocast, after its casts; convolutions as one op) is
recorded with the bytes it reads (each input tensor's extent in memory: a broadcast view counts once) and
writes (each output), its FLOPs (convolutions and matrix products, 2 per multiply-add, from
``torch.utils.flop_counter``; elementwise work counts as memory), whether it is a dtype cast, its output dtype,
and for convolutions whether the input is NHWC and whether the channel counts are multiples of 8. Views
(same storage as an input, not in place) move nothing. What the GPU's kernels do inside one op (cuDNN's
workspaces, layout conversions it makes itself) is not seen: this is the traffic of the list of operations.
"""

from dataclasses import dataclass, field

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_flatten
from torch.utils.flop_counter import flop_registry

CASTS = {"_to_copy", "to", "_to_dtype"}
ALLOCATIONS = {"empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided"}
CONVS = {"conv1d", "conv2d", "conv3d", "convolution", "_convolution", "cudnn_convolution", "convolution_overrideable",
         "mkldnn_convolution"}  # under inference mode the dispatcher sees conv2d itself (and ``to``, not _to_copy)


def extent_bytes(t: torch.Tensor) -> int:
    """Bytes of memory a tensor spans (a broadcast or strided view counts what it touches at most)."""
    if t.numel() == 0:
        return 0
    span = 1 + sum((size - 1) * abs(stride) for size, stride in zip(t.shape, t.stride()))
    return min(span, t.numel()) * t.element_size()


def nhwc(t: torch.Tensor) -> bool:
    """Stored channels-last (NHWC, NDHWC), and not just as well NCHW (one channel, or one pixel)."""
    if t.dim() not in (4, 5):
        return False
    layout = torch.channels_last if t.dim() == 4 else torch.channels_last_3d
    pixels = t[0, 0].numel()
    return t.is_contiguous(memory_format=layout) and not (t.shape[1] > 1 and pixels > 1 and t.is_contiguous())


@dataclass
class Op:
    name: str
    read: int  # bytes
    written: int
    flop: int = 0
    cast: bool = False
    dtype: str = ""  # of the (first) output
    conv_nhwc: bool | None = None  # convolutions: input stored NHWC
    conv_aligned: bool | None = None  # convolutions: in (per group) and out channels multiples of 8
    shape: tuple = ()

    @property
    def bytes(self) -> int:
        return self.read + self.written


@dataclass
class Counter(TorchDispatchMode):
    ops: list = field(default_factory=list)

    def __post_init__(self):
        super().__init__()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = func.overloadpacket.__name__
        inputs = [t for t in tree_flatten((args, kwargs))[0] if isinstance(t, torch.Tensor)]
        outputs = [t for t in tree_flatten(out)[0] if isinstance(t, torch.Tensor)]
        storages = {t.untyped_storage().data_ptr() for t in inputs}
        in_place = name.endswith("_") or "out" in kwargs
        if not in_place and outputs and all(o.untyped_storage().data_ptr() in storages for o in outputs):
            return out  # a view: nothing moves
        if name in ALLOCATIONS:
            return out  # memory reserved, not touched
        op = Op(name, sum(extent_bytes(t) for t in inputs), sum(extent_bytes(t) for t in outputs),
                dtype=str(outputs[0].dtype).replace("torch.", "") if outputs else "",
                shape=tuple(outputs[0].shape) if outputs else ())
        op.cast = (name in CASTS and inputs and outputs and inputs[0].dtype != outputs[0].dtype) or (
            name == "copy_" and len(inputs) > 1 and inputs[0].dtype != inputs[1].dtype)
        if name in CONVS and outputs:  # 2 per multiply-add: out elements x (in channels per group x kernel)
            op.flop = 2 * outputs[0].numel() * args[1][0].numel()  # weight (out, in/groups, *kernel)
        elif func.overloadpacket in flop_registry:
            flop_fn = flop_registry[func.overloadpacket]
            shapes = [a.shape if isinstance(a, torch.Tensor) else a for a in args]
            try:
                op.flop = int(flop_fn(*shapes, **{k: v for k, v in kwargs.items() if k != "out"},
                                      out_shape=outputs[0].shape if outputs else None))
            except TypeError:
                op.flop = int(flop_fn(*shapes, out_shape=outputs[0].shape))
        if name in CONVS:
            x, w = args[0], args[1]
            groups = x.shape[1] // w.shape[1]
            op.conv_nhwc = nhwc(x)
            op.conv_aligned = w.shape[0] % 8 == 0 and w.shape[1] % 8 == 0
            op.shape = (tuple(x.shape[1:2]) + tuple(w.shape[:2]) + (groups,))
        self.ops.append(op)
        return out


def count(run) -> list[Op]:
    """The ops of ``run()``, counted."""
    with Counter() as counter:
        run()
    return counter.ops


def extrapolate(small: list[Op], large: list[Op], pixels: tuple[float, float], target: float) -> list[Op]:
    """Each op's bytes and FLOPs at ``target`` pixels, linear in pixels through its values at the two sizes
    counted (the same list of operations at both: a fixed part, weights and tiny tensors, stays fixed)."""
    if [o.name for o in small] != [o.name for o in large]:
        raise ValueError("the two sizes ran different lists of operations: cannot extrapolate")
    (p0, p1) = pixels
    out = []
    for a, b in zip(small, large):
        def at(u, v):
            return max(0.0, u + (v - u) * (target - p0) / (p1 - p0))
        out.append(Op(b.name, at(a.read, b.read), at(a.written, b.written), at(a.flop, b.flop), b.cast, b.dtype,
                      b.conv_nhwc, b.conv_aligned, b.shape))
    return out
