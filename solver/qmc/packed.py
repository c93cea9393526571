"""Float arrays inside a JSON state, exactly and compactly: {"dtype": "<f8", "shape": [...], "base64": ...}
(the raw little-endian float64 bytes in base64: 10.7 bytes a number where a JSON list of floats takes
about 20, and encoded and decoded 2.7-3.7x faster).  The Yau–Niu state's points and log weights
(solver/qmc/yau_niu.py) are stored so; :func:`unpack` also reads the list form states were stored in
before.

Chosen by measurement (bench/yau_niu_state.py, bench/results/yau-niu-state.md; load 1.2-1.9 on 2
cores, one BLAS thread; medians of 7 of encode + orjson dumps + loads + decode, states after 57 rows):
4-D linear ring at 8192 points, 40 960 numbers: JSON lists 806 765 bytes in 7.3 ms, base64 437 026 in
2.0 ms, zlib (level 1) + base64 417 266 in 12.9 ms, byte-shuffled + zlib + base64 382 774 in 9.3 ms;
100 cubic sensors at 4096 points, 819 200 numbers: JSON lists 15.7 MB in 141 ms, base64 8.74 MB in
52 ms, zlib + base64 8.11 MB in 273 ms, shuffled + zlib 7.34 MB in 194 ms (base85: 10.0 bytes a number
but 26x base64's CPU).  Float64 mantissas barely compress (at most 16% saved, at 4-6x the CPU), so the
bytes are stored as they are.  Over HTTP a 100-state session's chunk of one row cost the server 318 ms
of CPU as lists, 137 ms so.
"""

from __future__ import annotations

import base64
import binascii
import math
from typing import Any

import numpy as np

from ..errors import InputError

DTYPE = "<f8"
FORMAT = '{"dtype": "<f8", "shape": [...], "base64": "<the little-endian float64 bytes>"}'


def pack(array: np.ndarray) -> dict[str, Any]:
    """The array (C order) as {"dtype": "<f8", "shape": [...], "base64": ...}: bit for bit."""
    data = np.ascontiguousarray(array, dtype=DTYPE)
    return {"dtype": DTYPE, "shape": list(data.shape),
            "base64": base64.b64encode(data.tobytes()).decode("ascii")}


def pack_finite(array: np.ndarray, minus_inf: bool = False) -> dict[str, Any] | list:
    """:func:`pack`, or the JSON list when the array holds NaN or infinity (-inf allowed where
    ``minus_inf``): the session store refuses a state of non-finite numbers before writing it, as it
    did when the state was lists, where base64 would hide them until the next read."""
    if minus_inf:
        bad = bool(np.isnan(array).any() or np.isposinf(array).any())
    else:
        bad = not bool(np.isfinite(array).all())
    return array.tolist() if bad else pack(array)


def unpack(value: Any, field: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """The float array :func:`pack` wrote (or a JSON list of numbers, the older form) of ``shape``
    (None: any length), as a new writable float64 array; InputError(``field``) when the value is
    neither, is of another shape, or its bytes do not match the shape.  (Finiteness: the caller's.)"""
    if value is None:
        raise InputError(field, f"required: {FORMAT}")
    if isinstance(value, dict):
        array = _unpack_binary(value, field)
    elif isinstance(value, list):
        try:
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise InputError(field, f"must be {FORMAT} or a list of numbers") from None
    else:
        raise InputError(field, f"must be {FORMAT} (or a list of numbers), got {type(value).__name__}")
    wanted = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if array.ndim != len(shape) or any(s not in (None, got)
                                       for s, got in zip(shape, array.shape, strict=True)):
        raise InputError(field, f"must have shape {wanted}, got {tuple(array.shape)}")
    return array


def _unpack_binary(value: dict[str, Any], field: str) -> np.ndarray:
    extra = sorted(set(value) - {"dtype", "shape", "base64"})
    if extra:
        raise InputError(field, f"unknown key(s) {extra}: must be {FORMAT}")
    if value.get("dtype") != DTYPE:
        raise InputError(f"{field}.dtype", f"must be {DTYPE!r} (little-endian float64), "
                                           f"got {value.get('dtype')!r}")
    shape = value.get("shape")
    if (not isinstance(shape, list) or not shape
            or not all(isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape)):
        raise InputError(f"{field}.shape", f"must be a list of non-negative integers, got {shape!r}")
    text = value.get("base64")
    if not isinstance(text, str):
        raise InputError(f"{field}.base64", f"must be a string (base64 of the {DTYPE} bytes)")
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise InputError(f"{field}.base64", "is not valid base64") from None
    expected = 8 * math.prod(shape)
    if len(raw) != expected:
        raise InputError(f"{field}.base64", f"holds {len(raw)} bytes; shape {shape} of float64 "
                                            f"needs {expected}")
    return np.frombuffer(raw, dtype=DTYPE).reshape(shape).astype(float)  # a writable, native-order copy
