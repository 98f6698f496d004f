"""One place that configures JAX for workcell: CPU, float64 (micrometre work needs it), and a
persistent compilation cache so repeated CLI runs do not recompile the same kernels
(`WORKCELL_JAX_CACHE` overrides its folder; set it to an empty string to disable)."""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

_cache = os.environ.get(
    "WORKCELL_JAX_CACHE",
    os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "workcell-jax"
    ),
)
if _cache:
    try:
        os.makedirs(_cache, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", _cache)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    except (OSError, AttributeError):  # read-only home or an older JAX: compile every time
        pass

import jax.numpy as jnp  # noqa: E402

__all__ = ["jax", "jnp"]
