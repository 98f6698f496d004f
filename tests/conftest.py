import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from hypothesis import settings  # noqa: E402

# `make test` (and CI) draw the same examples every run: a property test that fails there fails
# for everyone, not by luck. `make fuzz` draws new examples each run (HYPOTHESIS_PROFILE=fuzz) to
# look for inputs nobody tried yet; a failure it finds becomes a fixed case.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("fuzz", derandomize=False, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))
