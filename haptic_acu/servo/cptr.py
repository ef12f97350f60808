"""Pointers for compiled code called through one ``void*`` (a numba ``cfunc`` called from C, the HD
scheduler, or through ctypes): :func:`address_of` turns it into an integer and :func:`i64p` into an
int64 pointer, which ``numba.carray`` views as the address table that
:func:`haptic_acu.servo.state.address_table` wrote (and :func:`haptic_acu.servo.state.unpack` reads).
"""
from __future__ import annotations

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
