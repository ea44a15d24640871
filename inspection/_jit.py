"""Compilation options shared by the package's numba kernels."""

from __future__ import annotations

from typing import Any

# A kernel that allocates nothing is compiled without numba's runtime. With the
# runtime, each array a kernel hands to a helper, and each view it takes, is
# reference-counted with an atomic increment and decrement; numba removes those
# pairs within straight-line code only, so in a loop over pixels or queries that
# branches they stay, and cost more than the arithmetic around them. Without
# it, numba refuses at compile time anything that would need the runtime (an
# allocation, a view, an array returned), so the option cannot hide a leak.
NO_RUNTIME: dict[str, Any] = {"_nrt": False}
