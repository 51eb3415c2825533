"""Trained models' jitted functions, built once per model structure (matching and lifting share it)."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax

# Models are called through jit-compiled functions with their NNX GraphDef closed over, one per
# GraphDef: passed as a static argument, a GraphDef is hashed on every call, and hashing one
# costs about 70 µs (a twentieth of a frame's 3D stage). Equal GraphDefs share one function (and
# its compiled programs); the id cache keeps a strong reference, so an id is never reused.
_BOUND_BY_ID: dict[tuple, tuple] = {}
_BOUND_BY_VALUE: dict[tuple, Callable] = {}
_MAX_BOUND = 256


def bound_model_fn(fn: Callable, graphdef) -> Callable:
    """``jax.jit(functools.partial(fn, graphdef))``, built once per (fn, GraphDef).

    ``fn(graphdef, *args)`` must be a pure function of arrays besides its GraphDef.
    """
    hit = _BOUND_BY_ID.get((fn, id(graphdef)))
    if hit is not None and hit[0] is graphdef:
        return hit[1]
    if len(_BOUND_BY_ID) >= _MAX_BOUND:
        _BOUND_BY_ID.clear()
        _BOUND_BY_VALUE.clear()
    jitted = _BOUND_BY_VALUE.get((fn, graphdef))
    if jitted is None:
        jitted = _BOUND_BY_VALUE[(fn, graphdef)] = jax.jit(functools.partial(fn, graphdef))
    _BOUND_BY_ID[(fn, id(graphdef))] = (graphdef, jitted)
    return jitted
