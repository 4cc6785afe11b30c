"""When jit reuses a compiled program: the rule, in one place.

jax.jit compiles once per (function object, static arguments, input shapes and dtypes).
So everything jitted in this package is made by a factory cached on the things that
change the computation, and only those:

    @compiled_once                       # functools.lru_cache: hashable arguments only
    def make_chunk(cfg, model): ...      # returns the same jitted function for equal keys

    make_chunk(computation_of(cfg, HOST_ONLY_FIELDS), model)

- Configs are frozen dataclasses (hashable, equal by value). `computation_of` resets the
  fields that only the host reads (directories, seeds, budgets, logging cadence) to their
  defaults, so runs that differ only in those share one program.
- Models are flax modules (frozen dataclasses): equal widths give equal keys.
- Policies (evaluation.Policy) come from cached factories, so a second evaluation of the
  same model reuses the compiled evaluation scan.
- Seeds and parameters are traced inputs, never static: a new seed never recompiles.
"""

from __future__ import annotations

import dataclasses
import functools
import inspect


def compiled_once(factory):
    """Cache a factory of jitted functions on its (hashable) arguments, bound to the
    factory's signature with its defaults filled in: f(cfg, model) and
    f(cfg, model, None) are one key (a bare lru_cache keys on how the call was spelled,
    and a second spelling compiled the same program again)."""
    signature = inspect.signature(factory)
    cached = functools.lru_cache(maxsize=16)(factory)

    @functools.wraps(factory)
    def call(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        return cached(*bound.args, **bound.kwargs)

    call.cache_info = cached.cache_info
    return call


def computation_of(cfg, host_only: tuple[str, ...]):
    """cfg with the host-only fields reset to their defaults (a compile-cache key)."""
    defaults = {f.name: f.default for f in dataclasses.fields(cfg) if f.name in host_only}
    return dataclasses.replace(cfg, **defaults)


def keep_only(cfg, fields: tuple[str, ...]):
    """A config of cfg's class with only `fields` copied (others default): the key of a
    computation that reads those fields alone."""
    return type(cfg)(**{f: getattr(cfg, f) for f in fields})
