"""A numba intrinsic that asks the CPU to start loading the cache line of an array element."""

from __future__ import annotations

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


@intrinsic
def prefetch(typingctx, arr, index):
    """Ask the CPU to start loading the cache line of ``arr[index]``.

    ``index`` is an integer (1-D arrays) or a tuple of integers. A hint only
    (LLVM's ``llvm.prefetch``): it never faults, changes no result and does
    not wait, so one loop can start many loads at once; an out-of-range
    index is allowed.
    """
    if not isinstance(arr, types.Array):
        return None
    if isinstance(index, types.Integer):
        if arr.ndim != 1:
            return None
    elif not (
        isinstance(index, types.BaseTuple)
        and len(index) == arr.ndim
        and all(isinstance(t, types.Integer) for t in index)
    ):
        return None
    sig = types.void(arr, index)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def,unused-ignore]
        aryty, idxty = signature.args
        ary = context.make_array(aryty)(context, builder, args[0])
        if isinstance(idxty, types.Integer):
            idx = [context.cast(builder, args[1], idxty, types.intp)]
        else:
            idx = [
                context.cast(builder, builder.extract_value(args[1], k), t, types.intp)
                for k, t in enumerate(idxty)
            ]
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, idx, wraparound=False)
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        # read, high temporal locality, data cache
        builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen
