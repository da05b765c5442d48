"""What the unit tests share: one JAX compilation cache for the run."""

import pytest


@pytest.fixture(scope="session", autouse=True)
def jax_compile_cache(tmp_path_factory) -> str:
    """JAX's persistent compilation cache in a fresh directory for this run (the planner's
    flight.control.ilqr.use_compile_cache): a solver or rollout that several tests, modules or
    subprocesses build alike is compiled once and loaded after. The executable loaded is the one
    compiled, so no result changes; the key holds the XLA options and flags, so tests that
    compare those still compile each. Subprocesses get the path (e.g. zenpilot predict
    --compile-cache-dir)."""
    from flight.control.ilqr import use_compile_cache
    return use_compile_cache(str(tmp_path_factory.mktemp("jax-compile-cache")))
