"""Arrays handed to compiled code through one pointer: a table of (address, rows, columns).

A numba ``cfunc`` called from C (the HD scheduler) or through ctypes receives a single ``void*``;
the intrinsics here turn the table's integers back into typed pointers, and ``numba.carray``
views them as arrays. The caller keeps the arrays alive and never reallocates them while the table
is in use.
"""
from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic


def _ptr_intrinsic(nbtype):
    @intrinsic
    def as_ptr(typingctx, addr):
        sig = types.CPointer(nbtype)(types.int64)

        def codegen(context, builder, signature, args):
            return builder.inttoptr(args[0], context.get_value_type(signature.return_type))

        return sig, codegen

    return as_ptr


f64p = _ptr_intrinsic(types.float64)
i64p = _ptr_intrinsic(types.int64)
i32p = _ptr_intrinsic(types.int32)


@intrinsic
def address_of(typingctx, ptr):
    """A void* as an int64 address."""
    sig = types.int64(types.voidptr)

    def codegen(context, builder, signature, args):
        return builder.ptrtoint(args[0], ir.IntType(64))

    return sig, codegen


def address_table(arrays: dict, spec) -> np.ndarray:
    """(address, rows, columns) for each ``(name, dtype, ndim)`` of ``spec``, in order; the arrays
    are checked for dtype, dimensions and C contiguity."""
    tbl = np.zeros(3 * len(spec), dtype=np.int64)
    for i, (name, dtype, ndim) in enumerate(spec):
        a = arrays[name]
        if a.dtype != dtype or a.ndim != ndim or not a.flags.c_contiguous:
            raise TypeError(f"array {name} must be C-contiguous {np.dtype(dtype).name} {ndim}-D, "
                            f"got {a.dtype} {a.ndim}-D contiguous={a.flags.c_contiguous}")
        tbl[3 * i] = a.ctypes.data
        tbl[3 * i + 1] = a.shape[0]
        tbl[3 * i + 2] = a.shape[1] if ndim == 2 else 0
    return tbl
