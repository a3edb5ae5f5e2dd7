"""The fast evaluator of a 2-D polynomial ``sum_{k,j} c[k, j] v^k u^j`` on numpy arrays (the kernel
behind :class:`envs.energy.power.PowerPolynomial`).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.floating[Any]]

HORNER_BLOCK = 8192  # elements per block: the (K * block) scratch stays in cache


class Horner2D:
    """Evaluation of ``sum_{k,j} c[k, j] v^k u^j`` with few numpy calls on flat arrays.

    Per block of at most ``HORNER_BLOCK`` elements: the powers ``u^0..u^(J-1)`` are formed as
    the rows of a ``(J, n)`` scratch array, one matrix product ``c @ U`` gives the K polynomials
    in ``u`` at once (BLAS), and Horner's scheme in ``v`` combines them into the output. About
    ``J + 2 K`` ufunc calls and one small GEMM per block, all on contiguous rows (several times
    faster than a Horner scheme of ufunc calls in both variables).
    """

    __slots__ = ("coef", "rows", "_typed", "_local")

    def __init__(self, coef: NDArray[np.float64]) -> None:
        self.coef = coef
        self.rows = tuple(tuple(float(c) for c in row) for row in coef)
        self._typed: dict[np.dtype[Any], FloatArray] = {}
        # scratch per thread and dtype: fresh large arrays every call would page-fault
        self._local = threading.local()

    def _scratch(self, dtype: np.dtype[Any], block: int) -> tuple[FloatArray, FloatArray]:
        cache = getattr(self._local, "cache", None)
        if cache is None:
            cache = self._local.cache = {}
        bufs = cache.get(dtype)
        if bufs is None or bufs[0].shape[1] < block:
            n_v, n_u = self.coef.shape
            bufs = cache[dtype] = (
                np.empty((n_u, block), dtype=dtype),
                np.empty((n_v, block), dtype=dtype),
            )
        return bufs

    def __call__(self, v: FloatArray, u: FloatArray, out: FloatArray) -> None:
        """Evaluate into ``out`` (1-D contiguous); ``v``, ``u``: 1-D of its size, or 0-d."""
        size = out.size
        if size == 0:
            return
        n_v, n_u = self.coef.shape
        dtype = out.dtype
        coef = self._typed.get(dtype)
        if coef is None:
            coef = self._typed[dtype] = np.ascontiguousarray(self.coef, dtype=dtype)
        block = min(size, HORNER_BLOCK)
        upow_buf, inner_buf = self._scratch(dtype, block)
        mul, add = np.multiply, np.add
        for start in range(0, size, block):
            stop = min(start + block, size)
            n = stop - start
            upow = upow_buf[:, :n] if n == upow_buf.shape[1] else np.empty((n_u, n), dtype=dtype)
            inner = inner_buf[:, :n] if n == inner_buf.shape[1] else np.empty((n_v, n), dtype=dtype)
            ub = u if u.ndim == 0 else u[start:stop]
            upow[0] = 1.0
            if n_u > 1:
                upow[1] = ub
            for j in range(2, n_u):
                mul(upow[j - 1], ub, out=upow[j])
            np.matmul(coef, upow, out=inner)
            vb = v if v.ndim == 0 else v[start:stop]
            ob = out[start:stop]
            if n_v == 1:
                ob[...] = inner[0]
                continue
            mul(inner[n_v - 1], vb, out=ob)
            for k in range(n_v - 2, 0, -1):
                add(ob, inner[k], out=ob)
                mul(ob, vb, out=ob)
            add(ob, inner[0], out=ob)


def _flat(a: NDArray[Any], shape: tuple[int, ...]) -> NDArray[Any]:
    """``a`` as a 1-D array of the broadcast shape's size (a 0-d array stays 0-d)."""
    if a.ndim == 0:
        return a
    if a.shape != shape:
        a = np.broadcast_to(a, shape)
    return a.reshape(-1)



def evaluate(
    plan: Horner2D,
    speed_mps: ArrayLike,
    accel_mps2: ArrayLike,
    out: FloatArray | None,
) -> FloatArray:
    """Evaluate ``plan`` at broadcast ``speed_mps``, ``accel_mps2`` (into ``out`` if given); float32
    when both inputs are float32, else float64."""
    v = speed_mps if isinstance(speed_mps, np.ndarray) else np.asarray(speed_mps)
    u = accel_mps2 if isinstance(accel_mps2, np.ndarray) else np.asarray(accel_mps2)
    if v.dtype == np.float32 and u.dtype == np.float32:
        dtype: type[np.floating[Any]] = np.float32
    else:
        dtype = np.float64
    shape = v.shape if v.shape == u.shape else np.broadcast_shapes(v.shape, u.shape)
    if (
        out is None
        and v.ndim > 1
        and v.shape == u.shape
        and v.strides == u.strides
        and v.flags.f_contiguous
        and not v.flags.c_contiguous
    ):
        # Fortran-ordered inputs (the env's (B, N) state): flatten in memory order, no copy
        result = np.empty(shape, dtype=dtype, order="F")
        plan(v.ravel(order="F"), u.ravel(order="F"), result.ravel(order="F"))
        return result
    vf, uf = _flat(v, shape), _flat(u, shape)
    if out is None:
        result = np.empty(shape, dtype=dtype)
        plan(vf, uf, result.reshape(-1))
        return result
    if not isinstance(out, np.ndarray) or out.dtype.kind != "f":
        raise TypeError("out must be a floating-point numpy array")
    if out.shape != shape:
        raise ValueError(f"out has shape {out.shape}, the arguments broadcast to {shape}")
    if (
        out.flags.c_contiguous
        and not np.may_share_memory(out, v)
        and not np.may_share_memory(out, u)
    ):
        plan(vf, uf, out.reshape(-1))
        return out
    result = np.empty(shape, dtype=out.dtype)
    plan(vf, uf, result.reshape(-1))
    out[...] = result
    return out
