"""Compiler flags and scalar primitives shared by the planner kernels."""

from __future__ import annotations

import sys
from collections.abc import Callable

from llvmlite import ir
from numba import njit
from numba.core import cgutils, cpu, types
from numba.core.options import TargetOptions
from numba.extending import intrinsic

# fastmath without 'nnan'/'ninf': the kernels rely on inf/NaN checks (infinite costs, safe controls). Only flags
# that act on one operation at a time ('nsz', 'arcp', 'afn'), so that a kernel's results do not depend on how
# numba happened to order its instructions. That order depends on what the process compiled before: numba names the
# variables of inlined functions with process-wide counters (the rollout kernel's loop-body arguments are
# `$simplex_corner_v288_..._0.2.870` in one process, `..._v286_..._0.2.790` in another), and the rollout kernel's
# machine code then differs with the process's history (302 or 298 multiplies). Its results may not:
# - 'contract' (dropped earlier) let LLVM fuse a multiply and an add into one FMA (one rounding instead of two)
#   wherever that order lets it: EDD5 on the tile circle gave 169.6, 166.3 or 163.3 mm from three caches;
# - 'reassoc' let it regroup sums and products by that order: a GP-MPPI closed loop (moving weights, delay
#   prediction) changed from its seventh cycle when the delay predictor and a plan were compiled first. Without
#   it the two processes' machine code still differs, but their commands are identical to the bit
#   (`tests/test_determinism.py` covers both).
# Cost: without 'contract' the planner was 5-9% slower; 'reassoc', see docs/benchmarks.md.
FASTMATH = {"nsz", "arcp", "afn"}


@njit(cache=True, inline="always")
def fmax(a: float, b: float) -> float:
    """max of two floats (Python's semantics: `a` unless `b > a`), written as a select.

    Not the builtin `max`: numba compiles its implementation once per process and type, as a function
    of its own that every later caller links, so its code depended on which function compiled it first
    and on what the numba cache held (seeded plans changed with the cache's history). A select is
    inlined into each caller and compiles to a branch-free maxsd there. numba's CUDA target compiles
    it too (it cannot compile float `max`)."""
    return b if b > a else a


@njit(cache=True, inline="always")
def fmin(a: float, b: float) -> float:
    """min of two floats (Python's semantics: `a` unless `b < a`; see `fmax`)."""
    return b if b < a else a


@intrinsic
def prefetch_row(typingctx, table, row):  # noqa: ANN001, ANN201 - numba intrinsic: typing context and numba types
    """Hint the CPU to fetch row `row` of the 2-D C-contiguous array `table` into the caches; returns nothing.

    `llvm.prefetch` (read, keep in all levels): unlike a load it does not hold up the instructions
    after it, so a group's table rows are requested before the work that does not need them and
    arrive while it runs. No bounds check: the caller passes a valid row (a prefetch never faults,
    but the caller's own read of the row follows).
    """
    if not (isinstance(table, types.Array) and table.ndim == 2 and isinstance(row, types.Integer)):
        return None
    sig = types.void(table, row)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        idx = context.cast(builder, args[1], signature.args[1], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx, zero], wraparound=False)
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [cgutils.voidptr_t, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0")
        builder.call(fn, [builder.bitcast(ptr, cgutils.voidptr_t), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


@intrinsic
def fetch_add(typingctx, counter, amount):  # noqa: ANN001, ANN201 - numba intrinsic: typing context and numba types
    """Atomically add `amount` to `counter[0]` (a 1-D int64 array) and return the value before the add.

    The CPU rollout workers take their next sample group from one shared counter with it, so the groups are
    spread over the threads as they free up (a thread slowed by another process takes fewer) without a lock
    or a round trip through Python. Which thread runs a group never changes what the group computes.
    """
    if not (isinstance(counter, types.Array) and counter.ndim == 1 and counter.dtype == types.int64
            and isinstance(amount, types.Integer)):
        return None
    sig = types.int64(counter, amount)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        aryty = signature.args[0]
        ary = context.make_array(aryty)(context, builder, args[0])
        zero = context.get_constant(types.intp, 0)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [zero], wraparound=False)
        val = context.cast(builder, args[1], signature.args[1], types.int64)
        return builder.atomic_rmw("add", ptr, val, "seq_cst")

    return sig, codegen


def _copy_inlined_ir_with_one_scope() -> None:
    """Have numba's inliner copy a callee's IR with one copy of its scope, not one per block.

    `InlineWorker.inline_ir` copies the callee's IR block by block, each with a `copy.deepcopy` of its own; every
    block holds the function's scope, so each block's copy copied the whole scope (every variable of the function)
    again: blocks x variables new `Var`s per copy, two copies per call site, ~2.5 million `Var`s in one planner
    configuration's compile. Here the blocks of one copy share one copy of the scope, as the blocks of the IR they
    are copied from share theirs."""
    import copy as copy_module

    from numba.core import inline_closurecall

    inline_ir = getattr(getattr(inline_closurecall, "InlineWorker", None), "inline_ir", None)
    code = getattr(inline_ir, "__code__", None)
    copy_ir = next((c for c in (code.co_consts if code else ()) if getattr(c, "co_name", "") == "copy_ir"), None)
    if copy_ir is None or not isinstance(getattr(inline_closurecall, "copy", None), type(copy_module)):
        return  # not the inliner this was written against: numba's own copies
    current: list = [None, None]  # the IR being copied now (kept alive, so its id is not reused) and its memo

    class _Copy:
        """numba's `copy` module for the inliner, with `deepcopy` sharing one memo within one `copy_ir` call."""

        def __getattr__(self, name: str) -> object:
            return getattr(copy_module, name)

        @staticmethod
        def deepcopy(x: object, memo: dict | None = None) -> object:
            if memo is None:
                frame = sys._getframe(1)
                if frame.f_code is copy_ir:
                    target = frame.f_locals.get("kernel_copy")
                    if current[0] is not target:
                        current[0], current[1] = target, {}
                    memo = current[1]
            return copy_module.deepcopy(x, memo)

    inline_closurecall.copy = _Copy()


_copy_inlined_ir_with_one_scope()


# numba's own flag that puts `noalias` on a function's pointer arguments (so on every array's data): its
# `parallel=True` lowering sets it on the loop bodies it outlines when it proves their arrays distinct, and without
# it LLVM vectorises no loop that writes one array and reads another (it cannot rule out that they overlap). numba
# does not let `njit` set it, so the option is mapped here, once, for the kernels' phases (`phase`), whose callers
# pass distinct buffers.
if not hasattr(cpu.CPUTargetOptions, "noalias"):
    cpu.CPUTargetOptions.noalias = TargetOptions.Mapping("noalias")


def phase(func: Callable) -> Callable:
    """Compile one phase of a rollout kernel: fastmath as the kernels, no reference counting (a phase allocates
    nothing, and the counts of the arrays passed per call cost more than the work), and `noalias` on its arrays.

    A phase must never be given the same array twice where one of them is written."""
    return njit(cache=True, fastmath=FASTMATH, _nrt=False, noalias=True)(func)


def vector_phase(func: Callable) -> Callable:
    """A `phase` with numpy's error model: a float division is not checked for zero, a check whose branch keeps
    LLVM from vectorising the loop around it. Only for phases whose divisors cannot be zero."""
    return njit(cache=True, fastmath=FASTMATH, _nrt=False, noalias=True, error_model="numpy")(func)


def _int64_vector(array: types.Type) -> bool:
    return isinstance(array, types.Array) and array.ndim == 1 and array.dtype == types.int64


def _element_pointer(context, builder, signature, args):  # noqa: ANN001, ANN202 - numba codegen arguments
    """The pointer to `array[index]` of an intrinsic whose first two arguments are a 1-D array and an index (no
    bounds check): what the atomic loads, stores and read-modify-writes below act on."""
    aryty = signature.args[0]
    ary = context.make_array(aryty)(context, builder, args[0])
    idx = context.cast(builder, args[1], signature.args[1], types.intp)
    return cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)


@intrinsic
def load_acquire(typingctx, array, index):  # noqa: ANN001, ANN201 - numba intrinsic: typing context and numba types
    """`array[index]` of a 1-D int64 array, read with acquire ordering (no bounds check).

    Paired with `store_release`: a thread that reads the value another thread stored with it also sees every
    write that thread made before the store (the lazily collapsed GP table's slabs, `lazy_collapse.ensure_block`).
    On x86 it is a plain load that the compiler may not move later loads above.
    """
    if not (_int64_vector(array) and isinstance(index, types.Integer)):
        return None
    sig = types.int64(array, index)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        ptr = _element_pointer(context, builder, signature, args)
        return builder.load_atomic(ptr, "acquire", 8)

    return sig, codegen


@intrinsic
def store_release(typingctx, array, index, value):  # noqa: ANN001, ANN201 - numba intrinsic
    """`array[index] = value` on a 1-D int64 array with release ordering (no bounds check): every write this
    thread made before it is seen by a thread that reads the value with `load_acquire`."""
    if not (_int64_vector(array) and isinstance(index, types.Integer) and isinstance(value, types.Integer)):
        return None
    sig = types.void(array, index, value)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        ptr = _element_pointer(context, builder, signature, args)
        val = context.cast(builder, args[2], signature.args[2], types.int64)
        builder.store_atomic(val, ptr, "release", 8)
        return context.get_dummy_value()

    return sig, codegen


_F32X4 = ir.VectorType(ir.FloatType(), 4)


@intrinsic
def row_axpy(typingctx, acc, weight, flat, start):  # noqa: ANN001, ANN201 - numba intrinsic
    """`acc + weight * flat[start:start + 4]` in float32, the four values as one vector: a table row of four values
    read with one load and weighed with one multiply and one add (`acc` None: `weight * row` alone). Returns the four
    sums as a tuple. No bounds check: the caller passes a row inside `flat`.

    Each value is rounded as the scalar `acc[i] + weight * flat[start + i]` (one multiply, then one add; no fused
    multiply-add), so the sums are those of four scalar chains to the bit. A vector-typed instruction in a loop also
    keeps LLVM's loop vectoriser off that loop: the GP rows' reads (`cpu_backend._read_rows`) were vectorised
    across samples into gathers, one value of eight rows each, which took 1.7x the time of a row at a time."""
    f32 = types.float32
    quad = types.UniTuple(f32, 4)
    if not (isinstance(flat, types.Array) and flat.ndim == 1 and flat.dtype == f32 and flat.layout == "C"
            and weight == f32 and isinstance(start, types.Integer) and (acc == quad or acc == types.none)):
        return None
    sig = quad(acc, weight, flat, start)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
        acc_v, weight_v, flat_v, start_v = args
        aryty = signature.args[2]
        ary = context.make_array(aryty)(context, builder, flat_v)
        idx = context.cast(builder, start_v, signature.args[3], types.intp)
        ptr = cgutils.get_item_pointer(context, builder, aryty, ary, [idx], wraparound=False)
        row = builder.load(builder.bitcast(ptr, _F32X4.as_pointer()), align=4)
        i32 = ir.IntType(32)
        w4 = ir.Constant(_F32X4, ir.Undefined)
        for i in range(4):
            w4 = builder.insert_element(w4, weight_v, i32(i))
        out = builder.fmul(w4, row)
        if signature.args[0] != types.none:
            a4 = ir.Constant(_F32X4, ir.Undefined)
            for i in range(4):
                a4 = builder.insert_element(a4, builder.extract_value(acc_v, i), i32(i))
            out = builder.fadd(a4, out)
        return context.make_tuple(builder, signature.return_type,
                                  [builder.extract_element(out, i32(i)) for i in range(4)])

    return sig, codegen


def _atomic_extreme(op: str) -> Callable:
    """An intrinsic `(array, index, value)` that atomically lowers (`min`) or raises (`max`) the int64
    `array[index]` to `value` (a signed `atomicrmw`, no bounds check) and returns nothing."""

    def typer(typingctx, array, index, value):  # noqa: ANN001, ANN202 - numba intrinsic
        if not (_int64_vector(array) and isinstance(index, types.Integer) and isinstance(value, types.Integer)):
            return None
        sig = types.void(array, index, value)

        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            ptr = _element_pointer(context, builder, signature, args)
            val = context.cast(builder, args[2], signature.args[2], types.int64)
            builder.atomic_rmw(op, ptr, val, "monotonic")
            return context.get_dummy_value()

        return sig, codegen

    typer.__name__ = f"fetch_{op}"
    return intrinsic(typer)


# the rollout threads merge the bounds of the GP table cells they read into one shared box with these
# (`lazy_collapse.note_read`): once per thread and plan, so a lock-free update, no ordering needed
fetch_min = _atomic_extreme("min")
fetch_max = _atomic_extreme("max")
