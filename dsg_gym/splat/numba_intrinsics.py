"""LLVM-level helpers for the numba kernels: what numba's typed Python cannot say."""

from __future__ import annotations

from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

__all__ = ["borrow", "lowest_bit"]


@intrinsic
def lowest_bit(typingctx, x):
    """Index of the lowest set bit of the int64 ``x`` (LLVM ``cttz``; ``x`` must not be 0)."""
    if not isinstance(x, types.Integer):
        return None

    def codegen(context, builder, signature, args):
        v = context.cast(builder, args[0], signature.args[0], types.int64)
        return builder.cttz(v, ir.Constant(ir.IntType(1), 1))

    return types.int64(x), codegen


@intrinsic
def borrow(typingctx, arr):
    """The array ``arr`` without its owner (NRT meminfo and parent set to null): a view that costs no
    reference counting when it is indexed into sub-arrays. Valid only while ``arr`` is alive, so use it only on a
    kernel's arguments (the caller holds them). Inside a parallel kernel's loop numba passes arrays this way
    already; a serial twin that borrows its inputs gets the same cheap views (``composite_merged_serial``: 1.5x
    faster on ``DSGWorld-v0`` steps, 2x more with its per-tile scratch arrays borrowed too)."""
    if not isinstance(arr, types.Array):
        return None

    def codegen(context, builder, signature, args):
        src = context.make_array(signature.args[0])(context, builder, value=args[0])
        out = context.make_array(signature.return_type)(context, builder)
        cgutils.copy_struct(out, src)
        out.meminfo = cgutils.get_null_value(out.meminfo.type)
        out.parent = cgutils.get_null_value(out.parent.type)
        return out._getvalue()

    return arr(arr), codegen
