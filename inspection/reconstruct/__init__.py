"""Point clouds from the rig's four flash frames, by window matching of rectified stereo pairs.

Each stereo pair of the rig is rectified to look straight down at the belt,
matched coarsely (SGBM) and then to sub-pixel precision with windows fitted
one pixel at a time, first square, then warped by the surface's disparity
field; the pairs' points are triangulated and fused into one weighted cloud.
Once the part is aligned, its CAD at the fitted pose can shape the windows
of a second pass over the same frames.

The stages, one module each:

- :mod:`.params`: :class:`ReconstructParams`;
- :mod:`.pairs`: the rig's rectified pairs (:meth:`Reconstructor.build`);
- :mod:`.matching`: coarse matching, square windows and triangulation of a pair;
- :mod:`.warping`: windows warped by the measured field or a guide's;
- :mod:`.kernels`: the compiled window fits;
- :mod:`.guided`: :class:`Prior`, :class:`Guide`, the guided pass, the bends' rematch;
- :mod:`.fusion`: the pairs' points merged into the cloud;
- :mod:`.result`: :class:`Cloud` and its report;
- :mod:`.reconstructor`: :class:`Reconstructor`, its passes and their :class:`Matching`;
"""

from __future__ import annotations

from .guided import Guide, Prior
from .params import ReconstructParams
from .reconstructor import Matching, Reconstructor, reconstruct
from .result import (
    FLAG_EMPTY,
    FLAG_LOW_TEXTURE,
    FLAG_PAIR_SKIPPED,
    FLAG_SATURATED,
    FLAG_TOO_DARK,
    Cloud,
    PairReport,
    ReconstructionReport,
)

__all__ = [
    "FLAG_EMPTY",
    "FLAG_LOW_TEXTURE",
    "FLAG_PAIR_SKIPPED",
    "FLAG_SATURATED",
    "FLAG_TOO_DARK",
    "Cloud",
    "Guide",
    "Matching",
    "PairReport",
    "Prior",
    "ReconstructParams",
    "ReconstructionReport",
    "Reconstructor",
    "reconstruct",
]
