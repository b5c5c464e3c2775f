"""CHOLMOD's supernodal factor read where it lies, as a float32 (or float64) `SupernodalFactor` (docs/model.md
§12, "The chord step's arithmetic").

cvxopt hands a numeric factorisation to Python as a capsule holding
CHOLMOD's `cholmod_factor` and reads its values out only through
`getfactor`, which first converts the factor into a simplicial, symbolic
one: the object can no longer solve, the next factorisation analyses the
pattern again, and the conversion costs about as much as the
factorisation. A supernodal LLᵀ factor already stores each supernode's
rows and columns as one dense column-major block (CHOLMOD's `super`, `pi`,
`px`, `s`, `x`), the layout `SupernodalFactor` solves with, so the float32
copy is one cast of `x` (the float64 one a copy of it), and the factor
stays usable through cvxopt.

The struct is read by its documented layout (CHOLMOD 2 to 4, the one
cvxopt's wheels carry); every field the copy relies on is checked first
(a supernodal, real, double-precision LLᵀ factor of the expected order with
64-bit or 32-bit indices), and `supernodal_copy` gives None for anything
else, so the caller keeps solving through cvxopt.
"""

from __future__ import annotations

import ctypes

import numpy as np

from scissor_cli.solvers.supernodal import SupernodalFactor

_SIZE, _PTR, _INT = ctypes.c_size_t, ctypes.c_void_p, ctypes.c_int


class _CholmodFactor(ctypes.Structure):
    """`cholmod_factor` (cholmod_core.h, CHOLMOD 2.0 to 4.x)."""

    _fields_ = [("n", _SIZE), ("minor", _SIZE), ("Perm", _PTR), ("ColCount", _PTR), ("IPerm", _PTR),
                ("nzmax", _SIZE), ("p", _PTR), ("i", _PTR), ("x", _PTR), ("z", _PTR), ("nz", _PTR),
                ("next", _PTR), ("prev", _PTR), ("nsuper", _SIZE), ("ssize", _SIZE), ("xsize", _SIZE),
                ("maxcsize", _SIZE), ("maxesize", _SIZE), ("super", _PTR), ("pi", _PTR), ("px", _PTR),
                ("s", _PTR), ("ordering", _INT), ("is_ll", _INT), ("is_super", _INT), ("is_monotonic", _INT),
                ("itype", _INT), ("xtype", _INT), ("dtype", _INT), ("useGPU", _INT)]


#: CHOLMOD's codes: itype (CHOLMOD_INT, CHOLMOD_LONG), xtype CHOLMOD_REAL, dtype CHOLMOD_DOUBLE
_INDEX_TYPES = {0: np.int32, 2: np.int64}
_REAL, _DOUBLE = 1, 0

_capsule_name = ctypes.pythonapi.PyCapsule_GetName
_capsule_name.restype, _capsule_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
_capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
_capsule_pointer.restype, _capsule_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]


def _array(address: int, count: int, dtype) -> np.ndarray:
    """A copy of `count` values of `dtype` at `address` (CHOLMOD owns the memory and may free it later)."""
    buffer = (ctypes.c_char * (count * np.dtype(dtype).itemsize)).from_address(address)
    return np.frombuffer(buffer, dtype=dtype).copy()


def supernodal_copy(capsule, n: int, dtype=np.float32) -> SupernodalFactor | None:
    """A `SupernodalFactor` in `dtype` (float32 or float64) of the numeric factor in cvxopt's `capsule` (order
    n), or None when the capsule does not hold a supernodal real double LLᵀ factor of order n laid out as this
    module reads it."""
    name = _capsule_name(capsule)
    if name is None or not name.startswith(b"CHOLMOD FACTOR"):
        return None
    address = _capsule_pointer(capsule, name)
    if not address:
        return None
    f = _CholmodFactor.from_address(address)
    index = _INDEX_TYPES.get(f.itype)
    if (index is None or f.n != n or f.is_super != 1 or f.is_ll != 1 or f.xtype != _REAL or f.dtype != _DOUBLE
            or f.nsuper < 1 or not (f.x and f.super and f.pi and f.px and f.s and f.Perm)):
        return None
    S = f.nsuper
    starts = _array(f.super, S + 1, index).astype(np.int64)
    row_ptr = _array(f.pi, S + 1, index).astype(np.int64)
    block_ptr = _array(f.px, S + 1, index).astype(np.int64)
    # what the layout promises: the supernodes tile 0…n, each block is its rows × its columns
    heights, widths = np.diff(row_ptr), np.diff(starts)
    if (starts[0] != 0 or starts[-1] != n or row_ptr[-1] > f.ssize or block_ptr[-1] > f.xsize
            or np.any(widths < 1) or np.any(heights < widths) or np.any(np.diff(block_ptr) != heights * widths)):
        return None
    block_rows = _array(f.s, int(row_ptr[-1]), index).astype(np.int32)
    own = np.arange(n) - np.repeat(starts[:-1], widths)  # each column's place in its supernode
    if np.any(block_rows[np.repeat(row_ptr[:-1], widths) + own] != np.arange(n)):  # a block's own columns first
        return None
    perm = _array(f.Perm, n, index).astype(np.int64)
    buffer = (ctypes.c_double * int(block_ptr[-1])).from_address(f.x)
    blocks = np.frombuffer(buffer, dtype=np.float64).astype(dtype)  # the one copy (CHOLMOD owns x), cast on the way
    return SupernodalFactor(starts, row_ptr, block_ptr, block_rows, blocks, perm)
